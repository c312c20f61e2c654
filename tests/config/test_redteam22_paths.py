"""Red team 22: one file named twice. The bridge writes its audit log (and the files beside
it), its audit key and the e-stop latch; a config that made two of them one file loaded, and
`config check` said ok. `estop_state_path: audit.jsonl` then had the first e-stop replace the
audit log with the latch: the trail gone from the disk, the running log writing on into an
unlinked file, `audit verify` failing every tree head."""

from __future__ import annotations

from pathlib import Path

import pytest

from rcan_rtps.cli.main import main
from rcan_rtps.config import ConfigError, estop_state_file, load_config
from rcan_rtps.config._model import AUDIT_SIDECARS
from rcan_rtps.governance.audit import checkpoint_path
from rcan_rtps.governance.resume import point_path
from rcan_rtps.governance.treehead import public_key_path, tree_head_path

CONFIG = """\
robot: {ruri: rcan://registry.local/acme/bot/v1/abcdefgh01}
bridge:
  api:
    auth_token_env: RT_TOKEN
%(api)s
  safety:
    max_linear_vel: 1.0
    max_angular_vel: 1.0
%(safety)s
  audit:
    path: %(log)s
    key_path: %(key)s
%(audit)s
"""


def _write(tmp_path: Path, *, log: str = "audit/audit.jsonl", key: str = "audit/audit.key",
           safety: str = "", audit: str = "", api: str = "") -> Path:
    path = tmp_path / "robot.rcan.yaml"
    path.write_text(CONFIG % {"log": log, "key": key, "safety": safety, "audit": audit,
                              "api": api})
    return path


def _refused(path: Path) -> tuple[str, str]:
    with pytest.raises(ConfigError) as info:
        load_config(path, env={})
    [issue] = info.value.issues
    return issue.path, issue.message


@pytest.mark.parametrize(("settings", "at", "also"), [
    ({"safety": "    estop_state_path: audit/audit.jsonl"}, "$.bridge.audit.path",
     "bridge.safety.estop_state_path"),
    ({"key": "audit/audit.jsonl"}, "$.bridge.audit.path", "bridge.audit.key_path"),
    ({"key": "audit/estop.state"}, "$.bridge.audit.key_path",
     "bridge.safety.estop_state_path"),  # the latch's default place
    ({"key": "audit/audit.jsonl.pub"}, "$.bridge.audit.key_path",
     "bridge.audit.path (.pub)"),  # the public key written over the private one
    ({"safety": "    estop_state_path: audit/../audit/x/../audit.key"},
     "$.bridge.audit.key_path", "bridge.safety.estop_state_path"),
    ({"audit": "    witness: file://%(dir)s/audit/audit.jsonl"}, "$.bridge.audit.path",
     "bridge.audit.witness"),
    ({"safety": "    estop_state_path: robot.rcan.yaml"}, "$.bridge.safety.estop_state_path",
     "the config file"),
    ({"safety": "    estop_state_path: server.key",
      "api": "    tls: {cert: server.pem, key: server.key}"},
     "$.bridge.safety.estop_state_path", "bridge.api.tls.key"),
])
def test_a_file_the_bridge_writes_named_twice_is_refused(
        settings: dict[str, str], at: str, also: str, tmp_path: Path) -> None:
    settings = {k: v % {"dir": tmp_path} for k, v in settings.items()}
    path, message = _refused(_write(tmp_path, **settings))
    assert path == at
    assert f" is also {also}: the bridge writes it, so it must be a file of its own" in message


def test_a_link_to_a_file_the_bridge_writes_is_that_file(tmp_path: Path) -> None:
    (tmp_path / "audit").mkdir()
    (tmp_path / "latch").symlink_to(tmp_path / "audit" / "audit.jsonl")
    path, message = _refused(_write(tmp_path, safety="    estop_state_path: latch"))
    assert (path, message.split(" is also ")[1].split(":")[0]) == (
        "$.bridge.audit.path", "bridge.safety.estop_state_path")


def test_config_check_refuses_it_as_run_does(tmp_path: Path,
                                             capsys: pytest.CaptureFixture[str]) -> None:
    config = _write(tmp_path, safety="    estop_state_path: audit/audit.jsonl")
    for flags in ((), ("--file-only",)):  # the file's own fault, wherever it is checked
        assert main(["config", "check", *flags, str(config)]) == 1
        err = capsys.readouterr().err
        assert "$.bridge.audit.path: " in err and "Traceback" not in err


def test_files_the_bridge_only_reads_may_be_one(tmp_path: Path) -> None:
    """A self-signed certificate that is its own client CA: nothing is written there."""
    config = load_config(_write(tmp_path, api="    tls: {cert: s.pem, key: s.key, "
                                               "client_ca: s.pem}"), env={})
    assert config.bridge.api.tls is not None
    assert config.bridge.api.tls.cert == config.bridge.api.tls.client_ca


def test_distinct_files_load(tmp_path: Path) -> None:
    config = load_config(_write(tmp_path, safety="    estop_state_path: state/estop.state"),
                         env={})
    assert estop_state_file(config.bridge) == str(tmp_path / "state" / "estop.state")
    config = load_config(_write(tmp_path), env={})
    assert estop_state_file(config.bridge) == str(tmp_path / "audit" / "estop.state")


def test_the_sidecars_the_check_knows_are_those_the_log_keeps(tmp_path: Path) -> None:
    log = tmp_path / "audit.jsonl"
    kept = {checkpoint_path(log), point_path(log), tree_head_path(log), public_key_path(log)}
    assert kept == {tmp_path / f"audit.jsonl{suffix}" for suffix in AUDIT_SIDECARS}
