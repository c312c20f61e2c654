"""The public surface: each package's `__all__`, the exception trees, refused empty policies.

The expected export sets are written out so that adding or removing a public name is a
deliberate change to this file, not an accident of an import.
"""

from __future__ import annotations

import importlib
import inspect
import pkgutil
from types import ModuleType

import pytest

import rcan_rtps
from rcan_rtps.api import ApiServerError
from rcan_rtps.bridge import BridgeError
from rcan_rtps.config import ConfigError, loads_config
from rcan_rtps.conformance import ConformanceError
from rcan_rtps.events import EventsFrozenError
from rcan_rtps.governance import (
    AllOf,
    EmptyPolicyError,
    GovernanceError,
    PerAction,
    safety_policy,
)
from rcan_rtps.mcp_server import McpServerError
from rcan_rtps.rcan import RcanError
from rcan_rtps.rcan.actions import names
from rcan_rtps.ros import WireError

EXPECTED_EXPORTS: dict[str, set[str]] = {
    "rcan_rtps": {"__version__"},
    "rcan_rtps.ros": {
        "ActionClient",
        "ActionError",
        "AmbiguousReply",
        "ActionServer",
        "CdrDecodeError",
        "ClientGoal",
        "Codec",
        "Direction",
        "Durability",
        "Endpoint",
        "GoalResult",
        "GoalState",
        "GraphTimeout",
        "History",
        "IdlSyntaxError",
        "InvalidNameError",
        "QosError",
        "QosProfile",
        "Reliability",
        "RequestMapping",
        "RosGraph",
        "RosNode",
        "RosPublisher",
        "RosSubscription",
        "SampleTooLarge",
        "ServerGoal",
        "ServiceClient",
        "ServiceServer",
        "ServiceTimeout",
        "ServiceUnavailable",
        "TypeStore",
        "UnknownTypeError",
        "UnsupportedBindingError",
        "UnsupportedDistroError",
        "UnsupportedTypeError",
        "ValueFitError",
        "WireError",
        "deserialize",
        "serialize",
    },
    "rcan_rtps.ros.security": {
        "CertificateError",
        "EnclaveFiles",
        "Keystore",
        "KeystoreError",
        "PolicyError",
        "SecurityError",
        "SecurityRequest",
        "SecurityUnavailable",
        "SignatureError",
        "check",
        "create_enclave",
        "create_keystore",
        "create_permission",
        "cyclone_has_security",
        "list_enclaves",
        "participant_security",
        "request_from_env",
    },
    "rcan_rtps.ros.typesys": {
        "ActionType",
        "Collection",
        "Constant",
        "DdsTypes",
        "Field",
        "FieldType",
        "MessageType",
        "MessageValues",
        "ParsedFile",
        "Primitive",
        "ServiceType",
        "TypeStore",
        "parse_idl",
        "rihs01",
    },
    "rcan_rtps.governance": {
        "DEFAULT_ACTION_ROLES",
        "DEFAULT_RATE_LIMITS",
        "GENESIS",
        "SCOPES",
        "AllOf",
        "AuditError",
        "AuditEvent",
        "AuditIntegrityError",
        "AuditKeyError",
        "AuditLog",
        "AuditReceipt",
        "AuditRecord",
        "AuditWriteError",
        "AuthConfigError",
        "AuthenticationError",
        "ChainHead",
        "Check",
        "Clock",
        "Decision",
        "ArmsHeld",
        "DispatchResult",
        "Dispatcher",
        "EmptyPolicyError",
        "EstopGuard",
        "EstopMachine",
        "EstopStateError",
        "GovernanceError",
        "Governor",
        "HitlPolicy",
        "Idempotency",
        "JwtVerifier",
        "LatchFile",
        "ManualClock",
        "Notifier",
        "PendingCommand",
        "PerAction",
        "Principal",
        "RateLimiter",
        "Rejection",
        "RolePolicy",
        "SystemClock",
        "TokenAuthenticator",
        "VelocityLimit",
        "Violation",
        "WebhookNotifier",
        "Workspace",
        "finite_numbers",
        "has_scope",
        "load_or_create_key",
        "load_private_key",
        "load_public_key",
        "public_key_pem",
        "safety_policy",
        "verify",
        "verify_bytes",
    },
    "rcan_rtps.rcan": {
        "ACTIONS",
        "JWT_LEVELS",
        "M2M_TRUSTED",
        "M2M_TRUSTED_LEVEL",
        "SPOKEN",
        "STATUS_OF",
        "AnyRoleName",
        "Envelope",
        "Heartbeat",
        "RcanCommand",
        "RobotId",
        "Signature",
        "VersionIncompatibleError",
        "validate_message",
        # INVOKE / INVOKE_CANCEL (§19), AUTHORIZE (§16.4)
        "Authorization",
        "Invoke",
        "InvokeCancel",
        "InvokeResult",
        "InvokeStatus",
        "invoke_command",
        "reply_id",
        "skill_error",
        # §18's Capability Object Map (STATUS's `caps`, GET /api/skills)
        "Capability",
        "invoke_caps",
        "ActionName",
        "ActionParams",
        "ActionSpec",
        "AiInfo",
        "ArmJointParams",
        "Approval",
        "Authorize",
        "DecisionBody",
        "Effect",
        "EnvelopeCommand",
        "ErrorBody",
        "ErrorCode",
        "Fault",
        "ForeignPublisher",
        "GateableName",
        "InvalidRuriError",
        "Invariant",
        "Joints",
        "MoveParams",
        "NavigateParams",
        "Navigation",
        "NoParams",
        "NormalizedCommand",
        "Outcome",
        "PendingAuth",
        "Position",
        "RcanError",
        "RobotPosition",
        "Reason",
        "Role",
        "RoleName",
        "RosInfo",
        "Ruri",
        "SchemaValidationError",
        "ShortCommand",
        "Status",
        "Telemetry",
        "Velocity",
        "action_spec",
        "convert_at", "decode_object",
        "openapi_schemas",
        "parse_ruri",
        "validate_command",
        "validation_path",
        "whole",  # a msgspec pattern matched whole (config and the registry use it)
    },
    "rcan_rtps.rcan.actions": {
        "ACTIONS",
        "READS",
        "Reads",
        "not_understood",
        "numbers",
        "unreadable",
        "ActionName",
        "ActionSpec",
        "ArmJointParams",
        "Builder",
        "DockParams",
        "LockParams",
        "NoRoute",
        "RampedMove",
        "Effect",
        "EstopSignal",
        "GateableName",
        "GoalRoute",
        "Halt",
        "HitlDefault",
        "Hold",
        "Invariant",
        "MessageKit",
        "MoveParams",
        "NavigateParams",
        "NoParams",
        "PathPoint",
        "Publish",
        "RosRoute",
        "SendGoal",
        "StopParams",
        "action_spec",
        "goal_routes",
        "markdown_table",
        "names",
        "specs",
        "stopping_names",
        "with_effect",
    },
    "rcan_rtps.conformance": {
        "LEVELS",
        "Case",
        "ConformanceError",
        "Level",
        "MissingToken",
        "ProbeError",
        "Result",
        "Suite",
        "load_suite",
        "run_suite",
    },
    "rcan_rtps.config": {
        "ApiConfig",
        "ArmConfig",
        "AuditConfig",
        "BridgeConfig",
        "ConfidenceGate",
        "ConfigError",
        "ConfigIssue",
        "HitlConfig",
        "HitlGate",
        "ImageFeedConfig",
        "JwtConfig",
        "MotionConfig",
        "MotionLock",
        "PrincipalConfig",
        "RbacConfig",
        "RcanConfig",
        "RobotConfig",
        "Ros2Config",
        "SignaturePolicy",
        "SignaturesConfig",
        "SignerKey",
        "SafetyConfig",
        "SecurityConfig",
        "SkillConfig",
        "TlsConfig",
        "estop_state_file",
        "issuer_roles",
        "load_config",
        "loads_config",
        "plaintext_problem",
        "polygon_edges",
        "polygon_problem",
    },
    "rcan_rtps.api": {
        "ApiServer",
        "ApiServerError",
        "ApiSettings",
        "Authenticator",
        "GoalState",
        "GoalView",
        "RobotView",
        "bind",
        "build_app",
        "cert_principals",
        "server_ssl_context",
        "settings_from_config",
    },
    # Applications, run from the command line: deliberately no Python API.
    "rcan_rtps.bridge": {"Bridge", "BridgeError", "BridgeOptions", "BridgeState",
                         "BridgeStateError"},
    "rcan_rtps.cli": set(),
    "rcan_rtps.sim": set(),
    "rcan_rtps.mcp_server": {"McpServerError"},  # `rcan-rtps mcp`'s: no Python API beyond it
    # the operator console's static files, as the API serves them
    "rcan_rtps.console": {"CONTENT_TYPES", "CSP", "asset", "asset_names"},
}

# The one base of each subsystem; every exception class defined under it derives from it.
SUBSYSTEM_BASES: dict[str, type[Exception]] = {
    "ros": WireError,
    "governance": GovernanceError,
    "rcan": RcanError,
    "config": ConfigError,
    "api": ApiServerError,
    "bridge": BridgeError,
    "conformance": ConformanceError,
    "events": EventsFrozenError,
    "mcp_server": McpServerError,
}


def export_order(name: str) -> tuple[int, str]:
    """ruff's RUF022 order: SCREAMING_CASE, then CamelCase, then everything else."""
    group = 0 if name.isupper() else 1 if name[0].isupper() else 2
    return group, name


def all_modules() -> list[ModuleType]:
    names = [m.name for m in pkgutil.walk_packages(rcan_rtps.__path__, "rcan_rtps.")]
    # `__main__` runs the CLI when imported.
    return [importlib.import_module(n) for n in names if not n.endswith(".__main__")]


def test_every_package_is_listed() -> None:
    packages = {"rcan_rtps"} | {
        m.name for m in pkgutil.walk_packages(rcan_rtps.__path__, "rcan_rtps.") if m.ispkg
    }
    assert packages == set(EXPECTED_EXPORTS)


@pytest.mark.parametrize("package", sorted(EXPECTED_EXPORTS))
def test_all_is_sorted_unique_and_resolves(package: str) -> None:
    module = importlib.import_module(package)
    exported = module.__all__
    assert exported == sorted(exported, key=export_order)
    assert len(exported) == len(set(exported))
    missing = [name for name in exported if not hasattr(module, name)]
    assert not missing, f"{package}.__all__ names what it does not define: {missing}"


@pytest.mark.parametrize("package", sorted(EXPECTED_EXPORTS))
def test_all_is_the_expected_surface(package: str) -> None:
    exported = set(importlib.import_module(package).__all__)
    expected = EXPECTED_EXPORTS[package]
    assert exported - expected == set(), "new public names: add them here on purpose"
    assert expected - exported == set(), "public names removed: a breaking change"


def test_every_exception_derives_from_its_subsystem_base() -> None:
    strays = []
    for module in all_modules():
        subsystem = module.__name__.split(".")[1]
        for name, obj in vars(module).items():
            if not (inspect.isclass(obj) and issubclass(obj, BaseException)):
                continue
            if obj.__module__ != module.__name__:
                continue  # imported, checked where it is defined
            base = SUBSYSTEM_BASES.get(subsystem)
            if base is None or not issubclass(obj, base):
                strays.append(f"{module.__name__}.{name}")
    assert strays == []


def test_each_public_exception_is_exported_by_its_subsystem() -> None:
    for subsystem, base in SUBSYSTEM_BASES.items():
        package = importlib.import_module(f"rcan_rtps.{subsystem}")
        public = {
            name
            for name in package.__all__
            if inspect.isclass(getattr(package, name))
            and issubclass(getattr(package, name), BaseException)
        }
        assert base.__name__ in public
        assert all(issubclass(getattr(package, name), base) for name in public)


def test_an_empty_all_of_is_refused() -> None:
    with pytest.raises(EmptyPolicyError, match="at least one check"):
        AllOf()


def test_an_empty_per_action_is_refused() -> None:
    with pytest.raises(EmptyPolicyError, match="at least one action"):
        PerAction({})


def test_empty_policy_error_is_a_governance_value_error() -> None:
    assert issubclass(EmptyPolicyError, GovernanceError)
    assert issubclass(EmptyPolicyError, ValueError)


def test_safety_policy_from_config_checks_every_action() -> None:
    config = loads_config(
        'robot: {ruri: "rcan://registry.local/acme/bot/unit-0001"}\n'
        "bridge:\n"
        "  api: {auth_token_env: T}\n"
        "  safety: {max_linear_vel: 1.0, max_angular_vel: 0.5}\n",
        env={"T": "x" * 32},
    )

    class Unlatched:
        latched = False

    policy = safety_policy(config.bridge.safety, Unlatched(), "map")
    assert set(policy.policies) == set(names())
    assert all(isinstance(p, AllOf) and p.checks for p in policy.policies.values())


def test_a_config_without_velocity_limits_does_not_load() -> None:
    # Fail closed: no built-in "safe" speed exists, so the limits are required.
    with pytest.raises(ConfigError, match="max_linear_vel"):
        loads_config(
            'robot: {ruri: "rcan://registry.local/acme/bot/unit-0001"}\n'
            "bridge:\n  api: {auth_token_env: T}\n  safety: {}\n",
            env={"T": "x" * 32},
        )
