"""`rcan-rtps audit ...`: verify a log against its anchors, prove inclusion and consistency,
export the public key.

    audit verify FILE [--pubkey KEY] [--witness HEADS ...]
    audit prove FILE SEQ [--size N]              an inclusion proof (JSON) of entry SEQ
    audit prove --verify PROOF [--pubkey KEY | FILE]
    audit consistency FILE OLD [NEW]             a consistency proof (JSON) between two sizes
    audit consistency --verify PROOF [--pubkey KEY | FILE]
    audit export-pubkey KEYFILE

The key is `--pubkey` when given (pin it: the file beside the log is only as trustworthy as the
disk it is on), else `FILE.pub`, written beside the log by the bridge.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

from rcan_rtps.governance.audit import load_private_key, load_public_key, public_key_pem
from rcan_rtps.governance.errors import AuditError
from rcan_rtps.governance.treehead import public_key_path

_KEY_HELP = "PEM Ed25519 public key of the bridge (default: FILE.pub beside the log)"


def register(subparsers: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    audit = subparsers.add_parser("audit", help="check and prove the signed audit chain")
    actions = audit.add_subparsers(dest="audit_command", required=True)
    check = actions.add_parser(
        "verify", help="verify links, hashes, signatures, tree heads and the checkpoint")
    check.add_argument("file", metavar="FILE", help="the audit log (.jsonl)")
    check.add_argument("--pubkey", metavar="KEY", help=_KEY_HELP)
    check.add_argument("--witness", metavar="HEADS", action="append", default=[],
                       help="tree heads a witness received (JSON lines); repeatable")
    check.set_defaults(func=verify_command)
    prove = actions.add_parser("prove", help="inclusion proof of one entry (or --verify one)")
    prove.add_argument("file", metavar="FILE", nargs="?", help="the audit log (.jsonl)")
    prove.add_argument("seq", metavar="SEQ", nargs="?", type=int, help="the entry's seq")
    prove.add_argument("--size", type=int, metavar="N",
                       help="prove against the tree head of size N (default: the newest)")
    prove.add_argument("--verify", metavar="PROOF", help="check a proof made by `audit prove`")
    prove.add_argument("--pubkey", metavar="KEY", help=_KEY_HELP)
    prove.set_defaults(func=prove_command)
    consistent = actions.add_parser(
        "consistency", help="consistency proof between two tree sizes (or --verify one)")
    consistent.add_argument("file", metavar="FILE", nargs="?", help="the audit log (.jsonl)")
    consistent.add_argument("old", metavar="OLD", nargs="?", type=int, help="the older size")
    consistent.add_argument("new", metavar="NEW", nargs="?", type=int,
                            help="the newer size (default: the newest tree head's)")
    consistent.add_argument("--verify", metavar="PROOF",
                            help="check a proof made by `audit consistency`")
    consistent.add_argument("--pubkey", metavar="KEY", help=_KEY_HELP)
    consistent.set_defaults(func=consistency_command)
    export = actions.add_parser("export-pubkey", help="print the public key of a signing key")
    export.add_argument("keyfile", metavar="KEYFILE",
                        help="the bridge's Ed25519 signing key (bridge.audit.key_path)")
    export.set_defaults(func=export_pubkey_command)


def _key(args: argparse.Namespace) -> tuple[Any, str]:
    """The public key to check with and where it came from (None, '' when there is none)."""
    if args.pubkey:
        return load_public_key(args.pubkey), f"--pubkey {args.pubkey}"
    if args.file:
        beside = public_key_path(Path(args.file))
        if beside.exists():
            return load_public_key(beside), f"the key beside the log ({beside})"
    return None, ""


def _fail(message: str) -> int:
    print(f"FAIL {message}", file=sys.stderr)
    return 1


def verify_command(args: argparse.Namespace) -> int:
    from rcan_rtps.governance.logcheck import check_log

    try:
        pubkey, source = _key(args)
        report = check_log(Path(args.file), pubkey, [Path(w) for w in args.witness])
    except AuditError as exc:
        return _fail(str(exc))
    except OSError as exc:
        return _fail(f"cannot read {args.file}: {exc}")
    for note in report.notes:
        print(f"note: {note}", file=sys.stderr)
    if not report.ok:
        for problem in report.problems:
            print(f"FAIL {args.file}: {problem}", file=sys.stderr)
        return 1
    signed = (f"hashes and signatures (with {source})" if pubkey
              else "hashes only (signatures need --pubkey or FILE.pub)")
    heads = f"{report.heads} tree heads"
    if report.witnessed:
        heads += f" and {report.witnessed} witnessed"
    if report.newest is not None:
        heads += f" match (newest: size {report.newest.tree_size})"
    else:
        heads += " match"
    print(f"OK {args.file}: {report.entries} entries, {signed}; {heads}")
    return 0


def prove_command(args: argparse.Namespace) -> int:
    from rcan_rtps.governance.logcheck import check_inclusion, prove_inclusion

    try:
        if args.verify:
            pubkey, _ = _key(args)
            if pubkey is None:
                return _fail("checking a proof needs the log's key: --pubkey KEY or FILE")
            print(f"OK {check_inclusion(_read_json(args.verify), pubkey)}")
            return 0
        if args.file is None or args.seq is None:
            return _fail("give FILE SEQ, or --verify PROOF")
        pubkey, _ = _key(args)
        proof = prove_inclusion(Path(args.file), args.seq, pubkey, args.size)
    except AuditError as exc:
        return _fail(str(exc))
    except OSError as exc:
        return _fail(f"cannot read: {exc}")
    print(json.dumps(proof, indent=2))
    return 0


def consistency_command(args: argparse.Namespace) -> int:
    from rcan_rtps.governance.logcheck import check_consistency, prove_consistency

    try:
        if args.verify:
            pubkey, _ = _key(args)
            print(f"OK {check_consistency(_read_json(args.verify), pubkey)}")
            return 0
        if args.file is None or args.old is None:
            return _fail("give FILE OLD [NEW], or --verify PROOF")
        pubkey, _ = _key(args)
        proof = prove_consistency(Path(args.file), args.old, args.new, pubkey)
    except AuditError as exc:
        return _fail(str(exc))
    except OSError as exc:
        return _fail(f"cannot read: {exc}")
    print(json.dumps(proof, indent=2))
    return 0


def _read_json(path: str) -> Any:
    from rcan_rtps.governance.logcheck import ProofError

    try:
        return json.loads(Path(path).read_text())
    # (ValueError: JSONDecodeError, and a number of more digits than Python converts;
    # RecursionError: nested deeper than Python's json goes)
    except (UnicodeDecodeError, ValueError, RecursionError) as exc:
        raise ProofError(f"{path} is not JSON: {exc}") from exc


def export_pubkey_command(args: argparse.Namespace) -> int:
    if _is_public_key(args.keyfile):
        print(f"FAIL {args.keyfile} is a public key already: export-pubkey reads the bridge's "
              "signing key (bridge.audit.key_path)", file=sys.stderr)
        return 1
    try:
        key = load_private_key(args.keyfile)
    except AuditError as exc:
        print(f"FAIL {exc}", file=sys.stderr)
        return 1
    sys.stdout.write(public_key_pem(key).decode())
    return 0


def _is_public_key(path: str) -> bool:
    """Whether `path` is a PEM public key (the `.pub` beside the log), read only that far."""
    try:
        if not Path(path).is_file():  # (a FIFO would block the read)
            return False
        with open(path, "rb") as file:
            return file.read(64).lstrip().startswith(b"-----BEGIN PUBLIC KEY-----")
    except OSError:
        return False  # the key loader names what is wrong with it
