"""Errors of config loading.

    ConfigError          carries every ConfigIssue found (key path + YAML line), not just the first
"""

from __future__ import annotations

from collections.abc import Sequence

import msgspec


class ConfigIssue(msgspec.Struct, frozen=True):
    path: str
    line: int | None
    message: str

    def __str__(self) -> str:
        where = f"line {self.line}: " if self.line is not None else ""
        return f"{where}{self.path}: {self.message}"


class ConfigError(Exception):
    """Base of every error raised by `rcan_rtps.config`."""

    def __init__(self, source: str, issues: Sequence[ConfigIssue]) -> None:
        lines = "\n".join(f"  {source}:{issue}" for issue in issues)
        super().__init__(f"{source}: {len(issues)} config error(s)\n{lines}")
        self.source = source
        self.issues = list(issues)
