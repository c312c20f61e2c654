"""Constrained field types shared by the RCAN schemas and the action parameters."""

from __future__ import annotations

from typing import Annotated

import msgspec


def whole(body: str) -> str:
    """A msgspec `pattern` that a string must match whole. msgspec matches with `re.search`,
    and Python's `$` also matches before a final newline (`"elbow\\n"` passed
    `^[A-Za-z0-9_./-]+$`); the lookahead refuses that, and means the same in JSON Schema's
    (ECMA) regular expressions, where these patterns are published too."""
    return rf"^(?:{body})$(?!\n)"


# Finite floats only: NaN and ±Inf fail both bounds, and absurd magnitudes are schema errors.
Finite = Annotated[float, msgspec.Meta(ge=-1e9, le=1e9)]
Confidence = Annotated[float, msgspec.Meta(ge=0.0, le=1.0)]
ShortText = Annotated[str, msgspec.Meta(max_length=256)]
JointName = Annotated[
    str, msgspec.Meta(min_length=1, max_length=128, pattern=whole(r"[A-Za-z0-9_./-]+"))
]
MessageId = Annotated[str, msgspec.Meta(min_length=1, max_length=64)]
# A sender's clock in Unix ms: JSON integers have no bound, and one of 400 digits overflowed a
# float when made seconds (a 503 for every message, stops included). 1e14 ms is the 1e11 s the
# SDK's `timestamp` in seconds is bounded by.
TimestampMs = Annotated[int, msgspec.Meta(ge=0, le=10**14)]


class Strict(msgspec.Struct, forbid_unknown_fields=True, frozen=True):
    """Unknown fields are errors: a typo must not silently become a default."""


class ActionParams(Strict, frozen=True):
    """Base of every action's parameters (one subclass per action, see `rcan.actions`)."""
