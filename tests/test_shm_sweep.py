"""The sweep of Fast DDS segments killed rclpy peers leave: only new ones, only unheld ones."""

from __future__ import annotations

import mmap
import os
from pathlib import Path

from shm_sweep import segments, sweep


def _make(shm: Path, *names: str) -> None:
    for name in names:
        (shm / name).write_bytes(b"\0" * mmap.PAGESIZE)


def test_only_segments_made_since_and_held_by_nobody_go(tmp_path: Path) -> None:
    _make(tmp_path, "fastrtps_00aa", "fastrtps_00aa_el", "unrelated.bin")
    before = segments(tmp_path)
    assert before == {"fastrtps_00aa", "fastrtps_00aa_el"}
    _make(tmp_path, "fastrtps_0bad", "fastrtps_0bad_el", "fastdds_0c0c", "fastdds_0c0c_el",
          "fastdds_0d0d", "fastdds_0d0d_el", "fastrtps_zz")
    opened = os.open(tmp_path / "fastdds_0c0c", os.O_RDONLY)  # a live peer's open segment
    with open(tmp_path / "fastdds_0d0d", "r+b") as f:  # ... and a mapped one (fd closed)
        mapped = mmap.mmap(f.fileno(), mmap.PAGESIZE)
    try:
        removed = sweep(before, tmp_path)
    finally:
        os.close(opened)
        mapped.close()
    assert removed == ["fastrtps_0bad", "fastrtps_0bad_el"]
    assert {p.name for p in tmp_path.iterdir()} == {
        "fastrtps_00aa", "fastrtps_00aa_el", "unrelated.bin", "fastrtps_zz",
        "fastdds_0c0c", "fastdds_0c0c_el", "fastdds_0d0d", "fastdds_0d0d_el"}


def test_nothing_new_removes_nothing(tmp_path: Path) -> None:
    _make(tmp_path, "fastrtps_01")
    assert sweep(segments(tmp_path), tmp_path) == []
    assert (tmp_path / "fastrtps_01").exists()
