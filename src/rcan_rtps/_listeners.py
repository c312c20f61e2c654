"""Telling listeners: each is called; one that fails is logged, and the rest still run."""

from __future__ import annotations

import logging
from collections.abc import Callable, Iterable
from typing import Any


def tell_all(listeners: Iterable[Callable[..., None]], log: logging.Logger, what: str,
             *args: Any) -> None:
    # A listener (STATUS, metrics) is informative: it must never break what it listens to.
    for listener in list(listeners):
        try:
            listener(*args)
        except Exception:
            log.exception("%s listener failed", what)
