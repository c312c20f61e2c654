"""The action registry is the only list of actions: every surface derives from it.

Each surface below is read the way its user reads it (the OpenAPI document, the RBAC table,
what the WebSocket lets through its e-stop lane, the mDNS TXT record, /api/metrics, the docs),
and must list exactly the registry's actions. A source scan refuses hand-kept lists.
"""

from __future__ import annotations

import ast
import re
from pathlib import Path
from types import SimpleNamespace

import msgspec
import pytest

from rcan_rtps.api._intake import intake
from rcan_rtps.governance import DEFAULT_ACTION_ROLES, RolePolicy
from rcan_rtps.governance.hitl import NEVER_GATED
from rcan_rtps.rcan import ACTIONS, Effect, openapi_schemas
from rcan_rtps.rcan.actions import ActionSpec, HitlDefault, Invariant, markdown_table, specs
from rcan_rtps.rcan.actions.move import MoveParams, velocity

ROOT = Path(__file__).resolve().parents[2]
SRC = ROOT / "src" / "rcan_rtps"
REGISTRY = SRC / "rcan" / "actions"
NAMES = list(ACTIONS)


def test_registry_discovers_one_module_per_action() -> None:
    modules = sorted(p.stem for p in REGISTRY.glob("*.py") if not p.stem.startswith("_"))
    assert sorted(NAMES) == modules
    assert len(NAMES) >= 6
    for effect in (Effect.HALT, Effect.ESTOP, Effect.CLEAR_ESTOP):
        assert sum(s.effect is effect for s in specs()) == 1


def test_openapi_enum_lists_exactly_the_registry() -> None:
    schemas = openapi_schemas()
    for form in ("ShortCommand", "EnvelopeCommand"):
        assert sorted(schemas[form]["properties"]["action"]["enum"]) == sorted(NAMES)
    for spec in specs():  # every parameter type is in the document
        assert spec.params.__name__ in schemas


def test_rbac_table_is_the_registry() -> None:
    assert list(DEFAULT_ACTION_ROLES) == NAMES
    policy = RolePolicy()
    for spec in specs():
        assert policy.required(spec.name) is spec.default_role


def test_hitl_never_gates_what_stops_the_robot() -> None:
    assert {s.name for s in specs() if s.stopping} == set(NEVER_GATED)


@pytest.mark.parametrize("name", NAMES)
def test_every_transport_lane_follows_the_registry(name: str) -> None:
    # REST and the WebSocket share `intake`; its `stopping` puts a command in the e-stop lane.
    spec = ACTIONS[name]
    body = msgspec.json.encode({"action": name, "params": _example(spec)})
    item = intake(body, 65536)
    assert item.command is not None, item.detail
    assert item.stopping is spec.stopping


def test_unknown_actions_are_refused_at_the_boundary() -> None:
    item = intake(b'{"action": "self_destruct"}', 65536)
    assert item.command is None and item.refusal is not None
    assert item.refusal.reason == "$.action"


def test_mdns_caps_are_the_registry() -> None:
    from bridge.test_mdns import _config  # the TXT test's own config

    from rcan_rtps.bridge.mdns import txt_records

    txt = txt_records(_config(), api_url="http://10.0.0.5:8765")
    assert txt["caps"].split(",") == NAMES


def test_docs_table_is_generated_from_the_registry() -> None:
    text = (ROOT / "docs" / "actions.md").read_text()
    block = text.split("<!-- actions:begin -->\n", 1)[1].split("<!-- actions:end -->", 1)[0]
    assert block == markdown_table()
    listed = re.findall(r"^\| `([a-z_]+)` \|", block, re.MULTILINE)
    assert listed == NAMES


def test_metrics_list_the_registry() -> None:
    from prometheus_client import generate_latest

    from rcan_rtps.api._metrics import Metrics
    from rcan_rtps.events import Events

    governor = SimpleNamespace(audit=SimpleNamespace(audited=Events().audited))
    metrics = Metrics(governor, status=None)  # type: ignore[arg-type]
    text = generate_latest(metrics.registry).decode()
    assert re.findall(r'rcan_action_info\{action="([a-z_]+)"', text) == NAMES


def test_a_spec_that_could_not_fail_closed_cannot_be_declared() -> None:
    with pytest.raises(ValueError, match="no invariants"):
        ActionSpec(name="x", summary="", params=MoveParams, effect=Effect.MOTION,
                   default_role=ACTIONS["move"].default_role, ros=ACTIONS["move"].ros,
                   invariants=())
    with pytest.raises(ValueError, match="e-stop"):
        ActionSpec(name="x", summary="", params=MoveParams, effect=Effect.MOTION,
                   default_role=ACTIONS["move"].default_role, ros=ACTIONS["move"].ros,
                   invariants=(Invariant.FINITE,))
    with pytest.raises(ValueError, match="never be gated"):
        ActionSpec(name="x", summary="", params=MoveParams, effect=Effect.HALT,
                   default_role=ACTIONS["move"].default_role, ros=ACTIONS["move"].ros,
                   invariants=(Invariant.FINITE,), hitl=HitlDefault(gateable=True))
    assert velocity  # the move route's builder is importable from its module


# -- no hand-kept lists ---------------------------------------------------------------------


def _action_literals(tree: ast.AST) -> list[tuple[int, str]]:
    """Places that name actions by hand: collections of ≥2 names, or an action compared
    with / looked up by a literal name."""
    names = set(NAMES)
    found: list[tuple[int, str]] = []
    for node in ast.walk(tree):
        items: list[ast.expr | None] = []
        if isinstance(node, ast.List | ast.Tuple | ast.Set):
            items = list(node.elts)
        elif isinstance(node, ast.Dict):
            items = list(node.keys)
        literal = [i.value for i in items if isinstance(i, ast.Constant) and i.value in names]
        if len(literal) >= 2:
            found.append((node.lineno, f"collection of {literal}"))
        if isinstance(node, ast.Compare):
            sides = [node.left, *node.comparators]
            constants = [s.value for s in sides if isinstance(s, ast.Constant)
                         and s.value in names]
            mentions_action = any("action" in ast.unparse(s) for s in sides)
            if constants and mentions_action:
                found.append((node.lineno, f"comparison with {constants}"))
        if isinstance(node, ast.Call) and node.args and "action" in ast.unparse(node.func):
            first = node.args[0]
            if isinstance(first, ast.Constant) and first.value in names:
                found.append((node.lineno, f"lookup of {first.value!r}"))
    return found


def test_no_literal_list_of_actions_outside_the_registry() -> None:
    offenders = []
    for path in SRC.rglob("*.py"):
        if REGISTRY in path.parents:
            continue
        for line, what in _action_literals(ast.parse(path.read_text())):
            offenders.append(f"{path.relative_to(ROOT)}:{line}: {what}")
    assert offenders == []


def test_the_scan_finds_what_it_must() -> None:
    sample = ('A = ("move", "stop")\nif command.action == "navigate": pass\n'
              'roles = {"estop": 1, "clear_estop": 2}\nx = action_roles.get("estop")\n')
    assert len(_action_literals(ast.parse(sample))) == 4


def _example(spec: ActionSpec) -> dict[str, object]:
    """Valid parameters for any action: its own example, or a sample for each required field."""
    if spec.example is not None:
        return dict(spec.example)
    info = msgspec.inspect.type_info(spec.params)
    assert isinstance(info, msgspec.inspect.StructType)
    out: dict[str, object] = {}
    for field in (f for f in info.fields if f.required):
        kind = field.type
        if isinstance(kind, msgspec.inspect.ListType):
            item = kind.item_type
            out[field.name] = ["j1"] if isinstance(item, msgspec.inspect.StrType) else [0.1]
        else:
            out[field.name] = "j1" if isinstance(kind, msgspec.inspect.StrType) else 0.5
    return out
