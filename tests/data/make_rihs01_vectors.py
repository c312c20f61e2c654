"""Regenerates tests/data/rihs01_jazzy.json: official RIHS01 hashes shipped by ROS 2 Jazzy.

Every `share/<pkg>/<kind>/<Name>.json` of a ROS 2 install is a type description whose
`type_hashes` list holds the official hash of the interface and of every type it refers
to. For each interface of the rcan-rtps IDL bundle (`idl/`, top level = Jazzy) and of the
test IDL (`tests/data/idl/`) this script copies the hashes of the interface's own types
(`pkg/srv/S`, `S_Request`, `S_Response`, `S_Event`; the action parts; …). Nothing is
computed here; the values are copied as ROS ships them. Standard library only:

    python3 tests/data/make_rihs01_vectors.py [--share .cache/ros-jazzy/share]

Packages missing from the install (not on PyPI: nav2_msgs, tf2_msgs, …) are listed and
skipped; tests/data/make_rihs01_official.py hashes them with the official generator.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

HERE = Path(__file__).resolve().parent
ROOT = HERE.parents[1]
OUT = HERE / "rihs01_jazzy.json"
KINDS = ("msg", "srv", "action")


def interfaces(root: Path) -> list[str]:
    """`pkg/kind/Name` of every `.idl` under a bundle-like root (skipping `_distro`)."""
    found = []
    for pkg_dir in sorted(p for p in root.iterdir() if p.is_dir() and p.name[0] not in "_."):
        for kind in KINDS:
            paths = sorted(pkg_dir.glob(f"{kind}/*.idl"))
            found += [f"{pkg_dir.name}/{kind}/{p.stem}" for p in paths]
    return found


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--share", type=Path, default=ROOT / ".cache/ros-jazzy/share")
    args = parser.parse_args()

    hashes: dict[str, str] = {}
    absent: list[str] = []
    for interface in interfaces(ROOT / "idl") + interfaces(HERE / "idl"):
        pkg, kind, name = interface.split("/")
        path = args.share / pkg / kind / f"{name}.json"
        if not path.exists():
            absent.append(interface)
            continue
        doc = json.loads(path.read_text(encoding="utf-8"))
        own = [
            h
            for h in doc["type_hashes"]
            if h["type_name"] == interface or h["type_name"].startswith(interface + "_")
        ]
        if not own:
            raise SystemExit(f"{path}: no hash for {interface}")
        for entry in own:
            hashes[entry["type_name"]] = entry["hash_string"]
    out = {
        "_generated_by": "tests/data/make_rihs01_vectors.py (see tests/data/README.md)",
        "_source": "type_hashes of share/<pkg>/<kind>/<Name>.json in ROS 2 Jazzy wheels (PyPI)",
        "hashes": dict(sorted(hashes.items())),
    }
    OUT.write_text(json.dumps(out, indent=1) + "\n", encoding="utf-8")
    print(f"wrote {len(hashes)} hashes to {OUT.relative_to(ROOT)}")
    if absent:
        print(f"not in this install ({len(absent)}): {', '.join(absent)}")


if __name__ == "__main__":
    main()
