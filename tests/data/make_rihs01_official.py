"""RIHS01 hashes of official interface files, computed by the official ROS 2 generator.

Runs under the Jazzy oracle's interpreter (it imports `rosidl_adapter` and
`rosidl_generator_type_description`, both from PyPI): each package under
tests/data/interfaces/ (not on PyPI; see SOURCES.md there) is translated to IDL by
`rosidl_adapter` and hashed by `rosidl_generator_type_description`, packages in dependency
order, types from installed packages read from the oracle's `share/`. Writes
`{"hashes": {type name: RIHS01}}` for every type each interface defines, by default as the
offline vectors tests/data/rihs01_official_jazzy.json:

    .cache/ros-jazzy/bin/python tests/data/make_rihs01_official.py [--out FILE] [--idl-out DIR]

`--idl-out` keeps the IDL `rosidl_adapter` wrote (the official restatement, with constants
and defaults). tests/ros/test_official_generator.py runs this live against the bundle;
tests/ros/test_kilted.py runs it under Kilted with `--interfaces tests/data/interfaces
tests/data/interfaces_distro/kilted` (Kilted's nav2_msgs replacing Jazzy's).
"""

from __future__ import annotations

import argparse
import contextlib
import io
import json
import re
import sys
import tempfile
from pathlib import Path

from rosidl_adapter import convert_to_idl
from rosidl_generator_type_description import generate_type_hash

HERE = Path(__file__).resolve().parent
OUT = HERE / "rihs01_official_jazzy.json"
KINDS = ("msg", "srv", "action")


def local_dependencies(packages: dict[str, Path]) -> dict[str, set[str]]:
    deps = {}
    for name, root in packages.items():
        text = "\n".join(p.read_text(encoding="utf-8") for p in root.glob("*/*.*"))
        deps[name] = {o for o in packages if o != name and re.search(rf"\b{o}/", text)}
    return deps


def build_order(packages: dict[str, Path]) -> list[str]:
    deps, order = local_dependencies(packages), []
    while len(order) < len(deps):
        ready = sorted(p for p, d in deps.items() if p not in order and d <= set(order))
        if not ready:
            raise SystemExit(f"dependency cycle among {sorted(set(deps) - set(order))}")
        order += ready
    return order


def translate(pkg: str, src: Path, idl_root: Path) -> list[str]:
    """`rosidl_adapter` .msg/.srv/.action → IDL; the generator's `root:relative` tuples."""
    tuples = []
    for kind in KINDS:
        for path in sorted((src / kind).glob(f"*.{kind}")):
            with contextlib.redirect_stdout(io.StringIO()):  # it narrates every file
                convert_to_idl(src, pkg, path.relative_to(src), idl_root / pkg)
            tuples.append(f"{idl_root / pkg}:{kind}/{path.stem}.idl")
    return tuples


def own_hashes(json_files: list[Path]) -> dict[str, str]:
    hashes = {}
    for path in json_files:
        doc = json.loads(path.read_text(encoding="utf-8"))
        interface = doc["type_description_msg"]["type_description"]["type_name"]
        for entry in doc["type_hashes"]:
            if entry["type_name"] == interface or entry["type_name"].startswith(interface + "_"):
                hashes[entry["type_name"]] = entry["hash_string"]
    return hashes


def official_hashes(interfaces: list[Path], share: Path, idl_root: Path,
                    work: Path) -> dict[str, str]:
    # a later folder's package replaces an earlier one's (another distro's version of it)
    packages = {p.name: p.resolve() for root in interfaces for p in sorted(root.iterdir())
                if p.is_dir()}
    includes = [f"{p.name}:{p}" for p in share.iterdir() if p.is_dir()]
    hashes: dict[str, str] = {}
    for pkg in build_order(packages):
        out = work / "json" / pkg
        args = {"package_name": pkg, "output_dir": str(out),
                "idl_tuples": translate(pkg, packages[pkg], idl_root),
                "include_paths": includes}
        args_file = work / f"{pkg}.json"
        args_file.write_text(json.dumps(args), encoding="utf-8")
        hashes.update(own_hashes([Path(p) for p in generate_type_hash(str(args_file))]))
        includes.append(f"{pkg}:{out}")
    return dict(sorted(hashes.items()))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--interfaces", type=Path, nargs="+", default=[HERE / "interfaces"],
                        help="folders of packages; a later one's package replaces an earlier's")
    parser.add_argument("--share", type=Path, default=Path(sys.prefix) / "share")
    parser.add_argument("--out", type=Path, default=OUT)
    parser.add_argument("--idl-out", type=Path, help="keep rosidl_adapter's IDL here")
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        idl_root = args.idl_out or Path(tmp) / "idl"
        hashes = official_hashes(args.interfaces, args.share, idl_root, Path(tmp))
    out = {
        "_generated_by": "tests/data/make_rihs01_official.py (see tests/data/README.md)",
        "_source": "rosidl_adapter + rosidl_generator_type_description (ROS 2 Jazzy, PyPI) "
        "run on tests/data/interfaces/ (official files, see SOURCES.md there)",
        "hashes": hashes,
    }
    args.out.write_text(json.dumps(out, indent=1) + "\n", encoding="utf-8")
    print(f"wrote {len(hashes)} hashes to {args.out}")


if __name__ == "__main__":
    main()
