"""`rcan-rtps audit verify FILE [--pubkey FILE]` and `rcan-rtps audit export-pubkey KEYFILE`."""

from __future__ import annotations

import argparse
import sys

from rcan_rtps.governance.audit import load_private_key, load_public_key, public_key_pem, verify
from rcan_rtps.governance.errors import AuditError


def register(subparsers: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    audit = subparsers.add_parser("audit", help="check and export the signed audit chain")
    actions = audit.add_subparsers(dest="audit_command", required=True)
    check = actions.add_parser("verify", help="verify links, hashes and (with --pubkey) signatures")
    check.add_argument("file", metavar="FILE", help="the audit log (.jsonl)")
    check.add_argument("--pubkey", metavar="FILE", help="PEM Ed25519 public key of the bridge")
    check.set_defaults(func=verify_command)
    export = actions.add_parser("export-pubkey", help="print the public key of a signing key")
    export.add_argument("keyfile", metavar="KEYFILE",
                        help="the bridge's Ed25519 signing key (bridge.audit.key_path)")
    export.set_defaults(func=export_pubkey_command)


def verify_command(args: argparse.Namespace) -> int:
    try:
        pubkey = load_public_key(args.pubkey) if args.pubkey else None
        head = verify(args.file, pubkey)
    except AuditError as exc:
        print(f"FAIL {exc}", file=sys.stderr)
        return 1
    except OSError as exc:
        print(f"FAIL cannot read {args.file}: {exc}", file=sys.stderr)
        return 1
    signed = "hashes and signatures" if pubkey else "hashes only (signatures need --pubkey)"
    print(f"OK {args.file}: {head.count} entries, {signed}; last {head.last_audit_id}")
    return 0


def export_pubkey_command(args: argparse.Namespace) -> int:
    try:
        key = load_private_key(args.keyfile)
    except AuditError as exc:
        print(f"FAIL {exc}", file=sys.stderr)
        return 1
    sys.stdout.write(public_key_pem(key).decode())
    return 0
