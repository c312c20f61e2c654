"""Counts kept per key (a principal's sockets or tickets, a sender's ids) that must not grow
with keys gone to zero: every key that ever held something would stay, one per name seen."""

from __future__ import annotations

from collections import Counter
from typing import TypeVar

K = TypeVar("K")


def count_down(counts: Counter[K], key: K) -> None:
    """One fewer of `key`; the key forgotten when none is left."""
    counts[key] -= 1
    if counts[key] <= 0:
        del counts[key]
