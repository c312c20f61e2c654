"""Writes one benchmark's section of docs/benchmarks.md, leaving the others as they are."""

from __future__ import annotations

from pathlib import Path

BENCHMARKS_MD = Path(__file__).resolve().parents[1] / "docs" / "benchmarks.md"


def write_section(title: str, markdown: str, path: Path = BENCHMARKS_MD) -> None:
    """Replaces the `title` section (a `## ` heading, included in `markdown`) or appends it."""
    path.parent.mkdir(exist_ok=True)
    text = path.read_text() if path.exists() else "# Benchmarks\n"
    head, sep, rest = text.partition(title)
    parts = [head.rstrip(), markdown.rstrip()]
    after = rest.split("\n## ", 1) if sep else []
    if len(after) > 1:
        parts.append("## " + after[1].rstrip())
    path.write_text("\n\n".join(parts) + "\n")
