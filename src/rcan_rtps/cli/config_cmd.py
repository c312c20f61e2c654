"""`rcan-rtps config check FILE`: exit 0 for a valid config, else print every issue and exit 1."""

from __future__ import annotations

import argparse
import os
import ssl
import sys
from collections.abc import Mapping

from rcan_rtps.config import ConfigError, RcanConfig, load_config
from rcan_rtps.governance.hitl import HitlPolicy
from rcan_rtps.governance.rbac import MIN_TOKEN_BYTES, shared_token_problem
from rcan_rtps.rcan import Role


def register(subparsers: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    config = subparsers.add_parser("config", help="work with .rcan.yaml files")
    actions = config.add_subparsers(dest="config_command", required=True)
    check = actions.add_parser(
        "check", help="validate a config file, listing every problem",
        description="Validates FILE, then checks what `rcan-rtps run` needs here: every token "
        "variable it names is set, its TLS files and JWT keys exist and load, the audit key, "
        "log and e-stop latch are files a start takes, and an existing audit log reads back as "
        "a start reads it (read only: beside a running bridge too). --file-only: the file "
        "alone, for a machine that will not run it.")
    check.add_argument("file", metavar="FILE", help="the .rcan.yaml to check")
    check.add_argument("--file-only", action="store_true",
                       help="check the file alone, not the token variables, TLS files and JWT "
                       "keys (for checking a config on a machine that will not run it)")
    check.set_defaults(func=check_command)


def check_command(args: argparse.Namespace) -> int:
    try:
        config = load_config(args.file)
    except ConfigError as exc:
        print(str(exc), file=sys.stderr)
        return 1
    failed = _report(f"{args.file}: valid, but no held command could ever be approved:",
                     approval_problems(config))
    if not args.file_only:
        failed |= _report(f"{args.file}: valid, but `rcan-rtps run` would fail here "
                          "(--file-only skips these checks):", run_problems(config, os.environ))
    if failed:
        return 1
    print(f"{args.file}: ok ({config.robot.ruri})")
    return 0


def _report(heading: str, problems: list[str]) -> bool:
    if problems:
        print(heading, file=sys.stderr)
        for problem in problems:
            print(f"  - {problem}", file=sys.stderr)
    return bool(problems)


def run_problems(config: RcanConfig, env: Mapping[str, str]) -> list[str]:
    """What stops `rcan-rtps run` with this config on this machine: tokens, TLS, JWT,
    principals' signing keys, and the files a start opens (the audit log read back too)."""
    problems: list[str] = []
    missing = missing_tokens(config, env)
    if missing:
        problems.append(f"token variables unset or shorter than {MIN_TOKEN_BYTES} bytes: "
                        f"{', '.join(missing)}")
    shared = shared_token_problem(config.bridge.api, env)
    if shared is not None:
        problems.append(f"bridge.api.principals: {shared}")
    return (problems + tls_problems(config) + jwt_problems(config) + signer_problems(config)
            + start_file_problems(config))


def approval_problems(config: RcanConfig) -> list[str]:
    """Gates whose n-of-m can never be met: fewer configured principals may approve than the
    gate needs, and no JWT issuer could bring more. Every such command would expire."""
    api, bridge = config.bridge.api, config.bridge
    if api.jwt is not None:
        return []  # JWT principals are not known in advance: any number may come
    roles = [Role[p.role] for p in api.principals]
    if not api.principals and api.auth_token_env:
        roles.append(Role.OWNER)  # the one default principal
    policy = HitlPolicy.from_config(bridge.hitl, bridge.rbac)
    problems = []
    for gate in bridge.hitl.gates:
        if not gate.require_auth:
            continue
        approver = policy.approver_role(gate.action)
        able = sum(1 for role in roles if role >= approver)
        if able < gate.approvals:
            problems.append(
                f"hitl.gates[{gate.action}]: needs {gate.approvals} distinct approvers of role "
                f"{approver.name} or higher, but only {able} configured principal(s) may "
                "approve: every held command would expire")
    return problems


def missing_tokens(config: RcanConfig, env: Mapping[str, str]) -> list[str]:
    """The token variables the config names that cannot authenticate anybody as they are."""
    api = config.bridge.api
    names = [p.token_env for p in api.principals if p.token_env]
    if not api.principals and api.auth_token_env:
        names.append(api.auth_token_env)
    return [n for n in dict.fromkeys(names)
            if len(env.get(n, "").encode()) < MIN_TOKEN_BYTES]


def _unreadable(key: str, path: str) -> str | None:
    """Why the file a config key names cannot be read, or None."""
    try:
        # Without blocking: a FIFO's open waits for a writer (the load names it, below).
        os.close(os.open(path, os.O_RDONLY | os.O_NONBLOCK))
        return None
    except OSError as exc:
        return f"{key}: cannot read {path}: {exc.strerror or exc}"


def tls_problems(config: RcanConfig) -> list[str]:
    """Missing or unreadable TLS files, else a certificate and key that do not load."""
    tls = config.bridge.api.tls
    if tls is None:
        return []
    named = {"cert": tls.cert, "key": tls.key, "client_ca": tls.client_ca}
    problems = [problem for key, path in named.items() if path is not None
                for problem in [_unreadable(f"bridge.api.tls.{key}", path)] if problem]
    if problems:
        return problems
    from rcan_rtps.api import server_ssl_context  # TLS configs only

    try:
        server_ssl_context(tls)
    except (ssl.SSLError, OSError, ValueError) as exc:
        return [f"bridge.api.tls: the certificate, key or client CA does not load: {exc}"]
    return []


def jwt_problems(config: RcanConfig) -> list[str]:
    """A JWT key file (PEM or JWKS) that is missing or holds no usable Ed25519 key."""
    jwt = config.bridge.api.jwt
    if jwt is None:
        return []
    from rcan_rtps.governance import AuthConfigError
    from rcan_rtps.governance.jwt import load_jwks, load_pem_key

    try:
        if jwt.jwks is not None:
            load_jwks(jwt.jwks)
        else:
            load_pem_key(jwt.public_key or "")
    except AuthConfigError as exc:
        return [f"bridge.api.jwt: {exc}"]
    return []


def signer_problems(config: RcanConfig) -> list[str]:
    """A principal's signing key (inline or file) that does not load as a key of its alg."""
    if not any(p.signatures for p in config.bridge.api.principals):
        return []
    from rcan_rtps.governance import AuthConfigError
    from rcan_rtps.governance.signatures import Signatures

    try:
        Signatures.from_config(config.bridge.api)
    except AuthConfigError as exc:
        return [f"bridge.api: {exc}"]
    return []


def start_file_problems(config: RcanConfig) -> list[str]:
    """The files a start opens (the audit key, the audit log, the e-stop latch, a file
    witness) as `run` judges them before it starts — the same list, all of it here — and an
    existing audit log read back as the start will (read only: beside a running bridge too).
    None there is fine: the first start makes them."""
    from rcan_rtps.governance.start_files import start_file_problems as problems_of

    notes: list[str] = []
    problems = problems_of(config.bridge, read_log_back=True, notes=notes)
    for note in notes:  # not a problem: unchecked, said so (a start reads it)
        print(f"note: {note}", file=sys.stderr)
    return [str(problem) for problem in problems]
