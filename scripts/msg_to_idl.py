"""Writes bundle IDL (idl/README.md's dialect) from official `.msg`/`.srv`/`.action` files.

The official interface files are facts: field order, names, types, defaults and constants.
This tool restates them in our compact IDL, dropping comments. Standard library only:

    python3 scripts/msg_to_idl.py PKG_DIR [PKG_DIR ...] [--out idl]

Each PKG_DIR is a package's interface folder (`<pkg>/msg/*.msg`, `srv/*.srv`,
`action/*.action`); its name is the package name. Check the result with the hash tests
(idl/README.md, "Adding a package").
"""

from __future__ import annotations

import argparse
import ast
import re
from dataclasses import dataclass
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PRIMITIVES = {
    "bool": "boolean", "byte": "octet", "char": "uint8", "float32": "float",
    "float64": "double", "string": "string", "wstring": "wstring",
    **{f"{s}int{n}": f"{s}int{n}" for s in ("", "u") for n in (8, 16, 32, 64)},
}
SECTIONS = {"msg": ("",), "srv": ("_Request", "_Response"),
            "action": ("_Goal", "_Result", "_Feedback")}
_TYPE = re.compile(r"^(?P<base>[\w/]+?)(?:<=(?P<sbound>\d+))?(?:\[(?P<arr>(?:<=)?\d*)\])?$")
_CONST = re.compile(r"^(?P<name>[A-Za-z]\w*)\s*=\s*(?P<value>.*)$")
_FIELD = re.compile(r"^(?P<name>[a-z]\w*)(?:\s+(?P<default>.+))?$")


@dataclass
class Member:
    idl_type: str  # element type in IDL (`string<5>`, `geometry_msgs::msg::Pose`)
    name: str
    array: str | None  # None, "" (sequence), "<=N" (bounded) or "N" (fixed)
    value: str | None  # constant value or default, as written in the .msg


def _strip_comment(line: str) -> str:
    quote = None
    for i, ch in enumerate(line):
        if quote:
            quote = None if ch == quote else quote
        elif ch in "\"'":
            quote = ch
        elif ch == "#":
            return line[:i].strip()
    return line.strip()


def _element(base: str, sbound: str | None, package: str) -> tuple[str, str | None]:
    """(IDL element type, `pkg/msg/Name` of a nested type or None)."""
    if base in PRIMITIVES:
        idl = PRIMITIVES[base]
        return (f"{idl}<{sbound}>" if sbound else idl), None
    if base == "Header":
        base = "std_msgs/Header"
    pkg, _, name = base.rpartition("/")
    pkg = pkg or package
    return f"{pkg}::msg::{name}", f"{pkg}/msg/{name}"


def parse_section(text: str, package: str, includes: list[str]) -> tuple[list[Member], ...]:
    constants: list[Member] = []
    fields: list[Member] = []
    for raw in text.splitlines():
        line = _strip_comment(raw)
        if not line:
            continue
        type_text, rest = line.split(None, 1)
        match = _TYPE.match(type_text)
        if not match:
            raise SystemExit(f"{package}: cannot read type {type_text!r}")
        idl, nested = _element(match["base"], match["sbound"], package)
        if nested and nested not in includes:
            includes.append(nested)
        const = _CONST.match(rest)
        if const:
            constants.append(Member(idl, const["name"], None, const["value"].strip()))
            continue
        field = _FIELD.match(rest)
        if not field:
            raise SystemExit(f"{package}: cannot read field {line!r}")
        fields.append(Member(idl, field["name"], match["arr"], field["default"]))
    return constants, fields


def _scalar(value: str, idl: str) -> str:
    if idl == "boolean":
        return "TRUE" if value.strip().lower() in ("true", "1") else "FALSE"
    if idl.startswith(("string", "wstring")):
        text = value.strip()
        if len(text) >= 2 and text[0] == text[-1] and text[0] in "\"'":
            text = ast.literal_eval(text)
        return '"' + text.replace("\\", "\\\\").replace('"', '\\"') + '"'
    return value.strip()


def _tuple_default(value: str, idl: str) -> str:
    text = re.sub(r"\b(true|false)\b", lambda m: m[0].capitalize(), value, flags=re.I)
    items = ast.literal_eval(text)
    if idl.startswith(("float", "double")):
        items = [float(v) for v in items]
    content = repr(tuple(items)).replace("\\", "\\\\").replace('"', '\\"')
    return f'"{content}"'


def _member_line(m: Member) -> str:
    decl = f"{m.idl_type} {m.name}"
    if m.array == "":
        decl = f"sequence<{m.idl_type}> {m.name}"
    elif m.array and m.array.startswith("<="):
        decl = f"sequence<{m.idl_type}, {m.array[2:]}> {m.name}"
    elif m.array:
        decl = f"{m.idl_type} {m.name}[{m.array}]"
    if m.value is None:
        return f"    {decl};"
    value = _scalar(m.value, m.idl_type) if m.array is None else _tuple_default(
        m.value, m.idl_type)
    return f"    @default (value={value}) {decl};"


def _struct(name: str, constants: list[Member], fields: list[Member]) -> list[str]:
    out = []
    if constants:
        out.append(f"  module {name}_Constants {{")
        out += [f"    const {c.idl_type} {c.name} = {_scalar(c.value or '', c.idl_type)};"
                for c in constants]
        out.append("  };")
    out.append(f"  struct {name} {{")
    out += [_member_line(f) for f in fields] or ["    uint8 structure_needs_at_least_one_member;"]
    out.append("  };")
    return out


def to_idl(path: Path, package: str) -> str:
    kind, name = path.parent.name, path.stem
    sections = re.split(r"^---\s*$", path.read_text(encoding="utf-8"), flags=re.M)
    if len(sections) != len(SECTIONS[kind]):
        raise SystemExit(f"{path}: expected {len(SECTIONS[kind])} sections")
    includes: list[str] = []
    body: list[str] = []
    for suffix, text in zip(SECTIONS[kind], sections, strict=True):
        body += _struct(name + suffix, *parse_section(text, package, includes))
    head = [f"// {package}/{kind}/{name} — rcan-rtps IDL bundle"]
    head += [f'#include "{inc}.idl"' for inc in includes]
    return "\n".join([*head, "", f"module {package} {{ module {kind} {{", *body, "}; };", ""])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("packages", nargs="+", type=Path)
    parser.add_argument("--out", type=Path, default=ROOT / "idl")
    args = parser.parse_args()
    for pkg_dir in args.packages:
        for kind, ext in (("msg", "msg"), ("srv", "srv"), ("action", "action")):
            for src in sorted((pkg_dir / kind).glob(f"*.{ext}")):
                dest = args.out / pkg_dir.name / kind / f"{src.stem}.idl"
                dest.parent.mkdir(parents=True, exist_ok=True)
                dest.write_text(to_idl(src, pkg_dir.name), encoding="utf-8")
                print(dest)


if __name__ == "__main__":
    main()
