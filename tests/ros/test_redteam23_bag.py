"""Red team 23 on `bag reindex` of a folder someone handed over: the names it writes its
rewrite and its metadata.yaml under before replacing (`.<file>.reindex`,
`.metadata.yaml.tmp`) are fixed, and were opened as found. A symbolic link there (a
tarball keeps one) had reindex truncate and overwrite the file it points to — any file of
the user running it — and a FIFO there held reindex for good."""

from __future__ import annotations

import os
import threading
from pathlib import Path

import pytest

from rcan_rtps.ros.bag import METADATA_FILE, BagError, reindex
from tests.ros.test_bag_hostile import _valid_bag

PLANTED = ["reindex", "metadata"]


def _planted_name(file: Path, which: str) -> Path:
    return file.with_name(f".{file.name}.reindex" if which == "reindex"
                          else f".{METADATA_FILE}.tmp")


@pytest.mark.parametrize("which", PLANTED)
def test_a_link_planted_at_reindex_s_temporary_name_is_not_written_through(
        tmp_path: Path, which: str) -> None:
    file = _valid_bag(tmp_path / "bag")
    victim = tmp_path / "precious.txt"
    victim.write_text("the user's own file\n")
    _planted_name(file, which).symlink_to(victim)
    (done,) = reindex(file.parent)
    assert done.messages == 20
    assert victim.read_text() == "the user's own file\n"  # before: the rewrite's bytes
    assert not _planted_name(file, which).exists()


@pytest.mark.parametrize("which", PLANTED)
def test_a_fifo_planted_at_reindex_s_temporary_name_does_not_hold_it(
        tmp_path: Path, which: str) -> None:
    file = _valid_bag(tmp_path / "bag")
    fifo = _planted_name(file, which)
    os.mkfifo(fifo)
    results: list[object] = []
    thread = threading.Thread(target=lambda: results.append(_reindexed(file.parent)),
                              daemon=True)
    thread.start()
    thread.join(20)
    stuck = thread.is_alive()
    if stuck:  # let it go: a reader opens the FIFO, the writer's open returns
        with open(fifo, "rb"):
            thread.join(5)
    assert not stuck, "reindex waited on the FIFO for a reader"
    assert results == [20]


def _reindexed(folder: Path) -> int | str:
    try:
        return reindex(folder)[0].messages
    except BagError as exc:
        return str(exc)
