"""A JointState as STATUS shows it: at most `MAX_JOINTS` joints, whatever the sender sent.

A JointState's size is bounded only by its sender, and STATUS is copied to every client many
times a second. The joints the bridge commands (the configured arms' joints) are listed first,
so a bound never hides what an operator moving the arm needs; the rest in the sample's order
up to the bound; `count` says how many the sample had.
"""

from __future__ import annotations

import itertools
from collections.abc import Sequence

from ..rcan import Joints
from .faults import cut_text

MAX_JOINTS = 64
MAX_JOINT_NAME = 256


def bounded_joints(names: Sequence[str], positions: Sequence[float],
                   velocities: Sequence[float], commanded: frozenset[str] = frozenset(),
                   limit: int = MAX_JOINTS) -> Joints:
    """The joints STATUS lists of one JointState (parallel lists, as the message has them;
    `positions` and `velocities` may be empty)."""
    count = len(names)
    if count <= limit and len(positions) <= limit and len(velocities) <= limit:
        return Joints([cut_text(n, MAX_JOINT_NAME) for n in names], list(positions),
                      list(velocities), count)
    first = [i for i in range(count) if names[i] in commanded][:limit]
    taken = set(first)
    rest = itertools.islice((i for i in range(count) if i not in taken), limit - len(first))
    chosen = sorted([*first, *rest])
    return Joints([cut_text(names[i], MAX_JOINT_NAME) for i in chosen],
                  _pick(positions, chosen, count, limit), _pick(velocities, chosen, count, limit),
                  count)


def _pick(values: Sequence[float], chosen: list[int], count: int, limit: int) -> list[float]:
    """The chosen joints' values when the list is the names' parallel, else (empty, or not
    matching the names: the sender's own inconsistency) its first `limit`."""
    if len(values) == count and count:
        return [values[i] for i in chosen]
    return list(values[:limit])
