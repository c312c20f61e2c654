"""Writes one benchmark's section of docs/benchmarks.md, leaving the others as they are; checks
out a baseline ref for the before-vs-after runs."""

from __future__ import annotations

import contextlib
import subprocess
import tempfile
from collections.abc import Iterator
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
BENCHMARKS_MD = ROOT / "docs" / "benchmarks.md"


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


@contextlib.contextmanager
def baseline_tree(ref: str) -> Iterator[Path]:
    """The `src` directory of `ref`, checked out into a temporary git worktree."""
    with tempfile.TemporaryDirectory(prefix="rcan-baseline-") as tmp:
        tree = Path(tmp) / "tree"
        subprocess.run(["git", "-C", str(ROOT), "worktree", "add", "--detach", "--quiet",
                        str(tree), ref], check=True)
        try:
            yield tree / "src"
        finally:
            subprocess.run(["git", "-C", str(ROOT), "worktree", "remove", "--force", str(tree)],
                           check=False)
