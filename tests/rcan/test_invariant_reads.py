"""Invariants declare the parameters they read; an action lacking them is refused when declared.

The registry holds only actions whose parameters every declared check can read (a property
over the real registry and over made-up actions); the checks' run-time side is in
tests/governance/test_invariants.py.
"""

from __future__ import annotations

import importlib.util
import sys
import textwrap
from pathlib import Path
from typing import Any

import msgspec
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from rcan_rtps.config import loads_config
from rcan_rtps.governance import Violation, safety_policy
from rcan_rtps.rcan import ACTIONS, ActionParams, Effect, Role, validate_command
from rcan_rtps.rcan.actions import (
    READS,
    ActionSpec,
    Invariant,
    NoRoute,
    not_understood,
    specs,
    unreadable,
)
from rcan_rtps.rcan.actions._invariants import Kind

MOVE = ACTIONS["move"]


class GoalWithoutY(ActionParams, frozen=True):
    x: float
    frame_id: str | None = None


class HalfAVelocity(ActionParams, frozen=True):
    linear_x: float = 0.0
    linear_y: float = 0.0  # no angular_z


def _declare(name: str, params: type[Any], *invariants: Invariant) -> ActionSpec[Any]:
    return ActionSpec(name=name, summary="test action", params=params, effect=Effect.MOTION,
                      default_role=Role.USER, ros=MOVE.ros,
                      invariants=(Invariant.ESTOP_GUARD, Invariant.FINITE, *invariants))


def test_a_workspace_check_without_its_parameters_is_refused_when_declared() -> None:
    with pytest.raises(ValueError, match=r"'dock_here'.*workspace check.*GoalWithoutY has no "
                                         r"field `y`"):
        _declare("dock_here", GoalWithoutY, Invariant.WORKSPACE)


def test_a_velocity_check_without_its_parameters_is_refused_when_declared() -> None:
    with pytest.raises(ValueError, match=r"'crawl'.*velocity check.*no field `angular_z`"):
        _declare("crawl", HalfAVelocity, Invariant.VELOCITY)


def test_a_parameter_of_a_kind_the_check_cannot_read_is_refused() -> None:
    class TextGoal(ActionParams, frozen=True):
        x: str
        y: float
        frame_id: str | None = None

    class MaybeVelocity(ActionParams, frozen=True):
        linear_x: float | None = None  # the velocity check cannot limit "no value"
        linear_y: float = 0.0
        angular_z: float = 0.0

    class Blob(ActionParams, frozen=True):
        data: bytes = b""

    with pytest.raises(ValueError, match=r"workspace check.*TextGoal.x is typed StrType"):
        _declare("t", TextGoal, Invariant.WORKSPACE)
    with pytest.raises(ValueError, match=r"velocity check.*MaybeVelocity.linear_x may be null"):
        _declare("t", MaybeVelocity, Invariant.VELOCITY)
    with pytest.raises(ValueError, match=r"finite check.*Blob.data holds values it cannot walk"):
        _declare("t", Blob)


def test_an_action_module_that_lacks_them_does_not_import(tmp_path: Path) -> None:
    """What adding such a module to the registry does: it fails at import, naming it all."""
    source = tmp_path / "dock_here.py"
    source.write_text(textwrap.dedent('''
        from rcan_rtps.rcan import ActionParams, Role
        from rcan_rtps.rcan.actions import ACTIONS, ActionSpec, Effect, Invariant

        class DockParams(ActionParams, frozen=True):
            dock_id: str

        SPEC = ActionSpec(name="dock_here", summary="dock", params=DockParams,
                          effect=Effect.MOTION, default_role=Role.USER,
                          ros=ACTIONS["navigate"].ros,
                          invariants=(Invariant.ESTOP_GUARD, Invariant.WORKSPACE))
    '''))
    spec = importlib.util.spec_from_file_location("dock_here_under_test", source)
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    with pytest.raises(ValueError) as info:
        spec.loader.exec_module(module)
    assert "dock_here" in str(info.value) and "workspace" in str(info.value)
    assert "`x`" in str(info.value)
    sys.modules.pop("dock_here_under_test", None)


# -- the registry: every declared check has its parameters ------------------------------------


def test_every_invariant_declares_what_it_reads() -> None:
    assert set(READS) == set(Invariant)


@settings(max_examples=200, suppress_health_check=[HealthCheck.too_slow])
@given(data=st.data())
def test_every_registered_action_has_what_its_checks_read(data: st.DataObject) -> None:
    spec = data.draw(st.sampled_from(list(specs())), label="action")
    for invariant in spec.invariants:
        assert unreadable(spec.params, invariant) is None, (spec.name, invariant)
    # Whatever the schema lets through for it, each declared check can read.
    body = data.draw(_bodies(spec), label="params")
    try:
        command = validate_command(msgspec.json.encode({"action": spec.name, "params": body}))
    except Exception:
        return  # refused at the boundary: no check ever sees it
    for invariant in spec.invariants:
        assert not_understood(command.params, invariant) is None, (spec.name, invariant)
    try:
        POLICY(command, command.params)
    except Violation as violation:  # refused on its merits, never for being unreadable
        assert violation.rejection.reason not in ("params_not_understood",
                                                  "safety_check_error"), violation


def _bodies(spec: ActionSpec[Any]) -> st.SearchStrategy[dict[str, Any]]:
    """The action's valid example with some fields replaced by arbitrary JSON values."""
    info = msgspec.inspect.type_info(spec.params)
    assert isinstance(info, msgspec.inspect.StructType)
    base = dict(spec.example or {})
    for field in info.fields:  # a plain value for any other required field
        if field.required and field.name not in base:
            text = isinstance(field.type, msgspec.inspect.StrType)
            base[field.name] = "x" if text else 0.5
    names = [f.name for f in info.fields]
    scalars = (st.none() | st.booleans() | st.integers(-3, 3) | st.floats(-2, 2)
               | st.sampled_from(["map", "odom", "elbow", "j1", "left", "x"]))
    json_values = scalars | st.lists(scalars, min_size=1, max_size=3) | st.dictionaries(
        st.sampled_from(["positions", "time_from_start_s"]), scalars, max_size=2)
    if not names:
        return st.just(base)
    changes = st.dictionaries(st.sampled_from(names), json_values, max_size=2)
    changes = st.one_of(changes, st.dictionaries(st.sampled_from(names), scalars, max_size=1))
    return changes.map(lambda changed: {**base, **changed})


def _policy() -> Any:
    config = loads_config(textwrap.dedent("""\
        robot: {ruri: "rcan://registry.local/acme/bot/unit-0001"}
        bridge:
          api: {auth_token_env: T}
          ros2:
            arms: {left: {topic: left/joint_trajectory, joints: [a, j1, elbow]}}
          safety:
            max_linear_vel: 1.0
            max_angular_vel: 1.0
            workspace: [[-10, -10], [10, -10], [10, 10], [-10, 10]]
        """), env={})
    return safety_policy(config.bridge.safety, _Unlatched(), "map", arms=config.bridge.ros2.arms)


class _Unlatched:
    latched = False


POLICY = _policy()


# -- made-up actions: declared iff every check can read them -----------------------------------

FIELD_TYPES: dict[str, tuple[Any, Any]] = {  # name of a type → (the type, a value of it)
    "float": (float, 0.5), "int": (int, 1), "str": (str, "a"), "bool": (bool, True),
    "float?": (float | None, None), "str?": (str | None, None), "list[str]": (list[str], ["a"]),
    "list[float]": (list[float], [0.5]), "bytes": (bytes, b"a"),
}
# What a check's Kind admits, from the type names above (the test's own statement of READS).
ADMITS = {Kind.NUMBER: {"float", "int"}, Kind.TEXT: {"str"}, Kind.TEXT_LIST: {"list[str]"}}
READ_NAMES = [*sorted({f.name for r in READS.values() for f in r.fields}), "other"]


def _expected_ok(fields: dict[str, str], invariants: list[Invariant]) -> bool:
    for invariant in invariants:
        reads = READS[invariant]
        for want in reads.fields:
            kind = fields.get(want.name)
            admitted = ADMITS[want.kind] | ({"float?"} if want.kind is Kind.NUMBER else set()
                                           ) | ({"str?"} if want.kind is Kind.TEXT else set())
            if kind is None or kind not in admitted:
                return False
            if kind.endswith("?") and not want.nullable:
                return False
        if reads.every_number and "bytes" in fields.values():
            return False
    return True


@settings(max_examples=300)
@given(fields=st.dictionaries(st.sampled_from(READ_NAMES), st.sampled_from(sorted(FIELD_TYPES)),
                              max_size=6),
       invariants=st.lists(st.sampled_from(list(Invariant)),
                           min_size=1, max_size=4, unique=True))
def test_made_up_actions_are_declared_only_if_their_checks_can_read_them(
    fields: dict[str, str], invariants: list[Invariant]
) -> None:
    params = msgspec.defstruct(
        "MadeUpParams",
        [(n, FIELD_TYPES[t][0], msgspec.field(default_factory=lambda v=FIELD_TYPES[t][1]: v))
         for n, t in fields.items()],
        bases=(ActionParams,), frozen=True)
    try:
        spec = ActionSpec(name="made_up", summary="", params=params, effect=Effect.LOCK,
                          default_role=Role.USER, ros=NoRoute(), invariants=tuple(invariants))
    except ValueError as exc:
        assert not _expected_ok(fields, invariants), exc
        assert "'made_up'" in str(exc) and "check" in str(exc)
        return
    assert _expected_ok(fields, invariants)
    value = params()  # declared: so every check can read what its type holds
    for invariant in spec.invariants:
        assert not_understood(value, invariant) is None
