"""The Cyclone configuration our domains get (participant.py): the values Cyclone applied,
read back from its own trace of its configuration."""

from __future__ import annotations

from pathlib import Path

import pytest

from rcan_rtps.ros.participant import RosNode


def applied(tmp_path: Path, monkeypatch: pytest.MonkeyPatch, domain_id: int,
            user: str = "") -> list[str]:
    """Cyclone's `config` trace lines of a node's domain made with `user` as CYCLONEDDS_URI."""
    trace = tmp_path / "config.trace"
    monkeypatch.setenv("CYCLONEDDS_URI", f"{user}<Tracing><Category>config</Category>"
                                         f"<OutputFile>{trace}</OutputFile></Tracing>")
    with RosNode("domain_config", "/", domain_id=domain_id, distro="jazzy"):
        pass
    return trace.read_text(errors="replace").splitlines()


def setting(lines: list[str], path: str) -> str:
    found = [line.split(f"{path}: ", 1)[1] for line in lines if f"{path}: " in line]
    assert len(found) == 1, f"{path} not in Cyclone's config trace once: {found}"
    return found[0].rsplit(" {", 1)[0]  # (the config sources that set it follow)


def test_a_reader_asks_again_for_a_lost_sample_every_100_ms(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch, domain_id: int) -> None:
    """Cyclone's default is 3 s, and Fast DDS writers send a HEARTBEAT every 3 s: a repair
    dropped at our socket again came 3 s later each time, past the repair window
    (docs/design/zero-loss.md, "Repairs dropped again")."""
    lines = applied(tmp_path, monkeypatch, domain_id)
    assert setting(lines, "Domain/Internal/AutoReschedNackDelay/#text") == "100 ms"


def test_the_user_s_cyclonedds_uri_overrides_it(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch, domain_id: int) -> None:
    user = "<Internal><AutoReschedNackDelay>2 s</AutoReschedNackDelay></Internal>"
    lines = applied(tmp_path, monkeypatch, domain_id, user)
    assert setting(lines, "Domain/Internal/AutoReschedNackDelay/#text") == "2 s"
