"""`rcan-rtps security …`: SROS2 keystores without ROS, like `ros2 security`."""

from __future__ import annotations

import argparse
import os
from pathlib import Path

KEYSTORE_HELP = "the keystore directory (public/, private/, enclaves/)"


def register(subparsers: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    parser = subparsers.add_parser(
        "security", help="SROS2 keystores, enclaves and permissions (like `ros2 security`)")
    verbs = parser.add_subparsers(dest="security_command", required=True)
    keystore = verbs.add_parser(
        "create-keystore", help="a new keystore: a CA and governance signed for the domain")
    keystore.add_argument("keystore", type=Path, metavar="KEYSTORE", help=KEYSTORE_HELP)
    keystore.set_defaults(func=create_keystore_command)
    enclave = verbs.add_parser(
        "create-enclave", help="an enclave's key, certificate and default permissions")
    enclave.add_argument("keystore", type=Path, metavar="KEYSTORE", help=KEYSTORE_HELP)
    enclave.add_argument("enclave", metavar="ENCLAVE", help="e.g. /robot1/rcan_bridge")
    enclave.set_defaults(func=create_enclave_command)
    permission = verbs.add_parser(
        "create-permission", help="an enclave's permissions from an SROS2 policy file")
    permission.add_argument("keystore", type=Path, metavar="KEYSTORE", help=KEYSTORE_HELP)
    permission.add_argument("enclave", metavar="ENCLAVE", help="an enclave of the keystore")
    permission.add_argument("policy", type=Path, metavar="POLICY",
                            help="an SROS2 policy XML (<policy version=\"0.2.0\">)")
    permission.set_defaults(func=create_permission_command)
    listing = verbs.add_parser("list-enclaves", help="the enclaves of a keystore")
    listing.add_argument("keystore", type=Path, metavar="KEYSTORE", help=KEYSTORE_HELP)
    listing.set_defaults(func=list_enclaves_command)
    check = verbs.add_parser(
        "check", help="check an enclave as a secured participant would (default: from "
        "ROS_SECURITY_KEYSTORE and ROS_SECURITY_ENCLAVE_OVERRIDE)")
    check.add_argument("keystore", type=Path, nargs="?", metavar="KEYSTORE",
                       help="default: ROS_SECURITY_KEYSTORE")
    check.add_argument("enclave", nargs="?", metavar="ENCLAVE",
                       help="default: ROS_SECURITY_ENCLAVE_OVERRIDE, else /")
    check.set_defaults(func=check_command)


def _domain_id(args: argparse.Namespace) -> int:
    from ..ros.participant import resolve_domain_id

    return resolve_domain_id(args.domain_id)


def create_keystore_command(args: argparse.Namespace) -> int:
    from ..ros.security import keystore

    domain_id = _domain_id(args)
    keystore.create_keystore(args.keystore, domain_id)
    print(f"keystore {args.keystore} (governance for domain {domain_id})")
    return 0


def create_enclave_command(args: argparse.Namespace) -> int:
    from ..ros.security import keystore

    directory = keystore.create_enclave(args.keystore, args.enclave, _domain_id(args))
    print(f"enclave {args.enclave} in {directory}")
    return 0


def create_permission_command(args: argparse.Namespace) -> int:
    from ..ros.security import keystore

    directory = keystore.create_permission(args.keystore, args.enclave, args.policy,
                                           _domain_id(args))
    print(f"permissions of {args.enclave} from {args.policy}: {directory / 'permissions.p7s'}")
    return 0


def list_enclaves_command(args: argparse.Namespace) -> int:
    from ..ros.security import keystore

    for name in keystore.list_enclaves(args.keystore):
        print(name)
    return 0


def check_command(args: argparse.Namespace) -> int:
    from ..ros.security import settings

    env = dict(os.environ)
    if args.keystore is not None:
        env[settings.KEYSTORE] = str(args.keystore)
    if args.enclave is not None:
        env[settings.ENCLAVE_OVERRIDE] = args.enclave
    request = settings.request_from_env("/", env)
    files = settings.EnclaveFiles.of(settings.locate(request))
    domain_id = _domain_id(args)
    settings.check(files, domain_id)
    print(f"enclave {request.enclave} in {files.directory}: usable on domain {domain_id}")
    if not settings.cyclone_has_security():
        print(f"but this Cyclone DDS has no DDS-Security: {settings.HOW_TO_GET_SECURITY}")
        return 1
    return 0
