"""Red team 22: the audit log and the e-stop latch at something that is no regular file.
`audit.path` at /dev/null (or a link to it) passed `config check`; `run` joined the domain,
then failed at its first entry with "Invalid argument". `estop_state_path` at /dev/null
passed too, and the latch's write renames a file over its path: run as root, the first e-stop
would have put a regular file in the place of the system's /dev/null. Now both are refused
before the start, by `config check` and `run` alike, and no state write replaces a device."""

from __future__ import annotations

import os
import stat
from pathlib import Path

import pytest

from rcan_rtps.bridge.runtime import Bridge, BridgeOptions
from rcan_rtps.cli.main import main
from rcan_rtps.config import load_config
from rcan_rtps.governance import AuditError
from rcan_rtps.governance._durable import atomic_write
from rcan_rtps.governance.audit import AuditLog

TOKEN = "t" * 32
CONFIG = """\
robot: {ruri: rcan://registry.local/acme/bot/v1/abcdefgh01}
bridge:
  api: {auth_token_env: RT22_TOKEN}
  safety:
    max_linear_vel: 1.0
    max_angular_vel: 1.0
    estop_state_path: %(latch)s
  audit: {path: %(log)s, key_path: audit.key}
"""


@pytest.fixture(autouse=True)
def token(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("RT22_TOKEN", TOKEN)


def _config(tmp_path: Path, *, log: str = "audit.jsonl", latch: str = "estop.state") -> Path:
    path = tmp_path / "robot.rcan.yaml"
    path.write_text(CONFIG % {"log": log, "latch": latch})
    return path


def _prepare_refuses(config: Path) -> str:
    bridge = Bridge(load_config(config, env={}),
                    BridgeOptions(port=0, mdns=False, env={"RT22_TOKEN": TOKEN}))
    with pytest.raises(Exception) as info:  # AuditError or EstopStateError
        bridge.prepare()
    return str(info.value)


def _fifo(path: Path) -> str:
    os.mkfifo(path, 0o600)
    return path.name


def _link_to_dev_null(path: Path) -> str:
    path.symlink_to(os.devnull)
    return path.name


@pytest.mark.parametrize("make", [_link_to_dev_null, _fifo])
def test_an_audit_log_that_is_no_regular_file_is_refused_before_the_start(
        make: object, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert callable(make)
    config = _config(tmp_path, log=make(tmp_path / "audit.jsonl"))
    assert main(["config", "check", str(config)]) == 1
    err = capsys.readouterr().err
    assert f"bridge.audit.path: audit log {tmp_path / 'audit.jsonl'} is not a regular file" in err
    assert "is not a regular file" in _prepare_refuses(config)


@pytest.mark.parametrize("make", [_link_to_dev_null, _fifo])
def test_a_latch_that_is_no_regular_file_is_refused_before_the_start(
        make: object, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert callable(make)
    config = _config(tmp_path, latch=make(tmp_path / "latch"))
    assert main(["config", "check", str(config)]) == 1
    err = capsys.readouterr().err
    assert (f"bridge.safety.estop_state_path: e-stop state {tmp_path / 'latch'} is not a "
            "regular file") in err
    assert "is not a regular file" in _prepare_refuses(config)


def test_the_default_latch_place_is_checked_too(tmp_path: Path) -> None:
    (tmp_path / "estop.state").mkdir()
    config = _config(tmp_path).read_text().replace("    estop_state_path: estop.state\n", "")
    (tmp_path / "robot.rcan.yaml").write_text(config)
    assert main(["config", "check", str(tmp_path / "robot.rcan.yaml")]) == 1


async def test_the_log_refuses_a_device_it_was_opened_on(tmp_path: Path) -> None:
    """The last word, for a file that became one after the check: nothing is appended to a
    file that keeps nothing."""
    (tmp_path / "a.jsonl").symlink_to(os.devnull)
    with pytest.raises(AuditError, match=r"a\.jsonl is not a regular file"):
        await AuditLog.open(tmp_path / "a.jsonl", tmp_path / "a.key")


def test_a_state_write_never_replaces_a_device(tmp_path: Path) -> None:
    device = tmp_path / "null"
    try:
        os.mknod(device, 0o600 | stat.S_IFCHR, os.makedev(1, 3))  # /dev/null's numbers
    except PermissionError:
        pytest.skip("making a device node needs root (CAP_MKNOD)")
    with pytest.raises(PermissionError, match="a device is never replaced"):
        atomic_write(device, b"{}")
    assert stat.S_ISCHR(os.lstat(device).st_mode)


def test_regular_files_and_none_at_all_pass(tmp_path: Path) -> None:
    config = _config(tmp_path)
    assert main(["config", "check", str(config)]) == 0
    (tmp_path / "audit.jsonl").write_bytes(b"")
    (tmp_path / "estop.state").write_text('{"latched": false}')
    assert main(["config", "check", str(config)]) == 0
