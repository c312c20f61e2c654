"""scripts/msg_to_idl.py restates official interface files as exactly the bundle's IDL.

Offline: the official files kept in tests/data/interfaces/ give, byte for byte, the bundle
files of their packages (so an edit to either side is noticed). With the oracle: the `.msg`,
`.srv` and `.action` files of every bundled package ROS 2 Jazzy ships on PyPI give the same
structs, constants and defaults as the bundle, including the files written by hand before
the tool existed.
"""

from __future__ import annotations

import dataclasses
import functools
import importlib.util
import sys
from pathlib import Path
from types import ModuleType

import pytest

from rcan_rtps.ros.typesys.idl_parser import parse_idl
from rcan_rtps.ros.typesys.model import MessageType
from rcan_rtps.ros.typesys.store import bundle_dir

from .offline_data import DATA

ROOT = Path(__file__).resolve().parents[2]
OFFICIAL = sorted(p for p in (DATA / "interfaces").iterdir() if p.is_dir())


@functools.cache
def _tool() -> ModuleType:
    spec = importlib.util.spec_from_file_location("msg_to_idl", ROOT / "scripts/msg_to_idl.py")
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # its dataclass looks itself up there
    spec.loader.exec_module(module)
    return module


def _sources(pkg_dir: Path) -> list[Path]:
    return sorted(p for kind in ("msg", "srv", "action") for p in pkg_dir.glob(f"{kind}/*.{kind}"))


@pytest.mark.offline
@pytest.mark.parametrize("pkg_dir", OFFICIAL, ids=lambda p: p.name)
def test_official_files_give_the_bundle_files_byte_for_byte(pkg_dir: Path) -> None:
    tool = _tool()
    sources = _sources(pkg_dir)
    bundled = sorted((bundle_dir() / pkg_dir.name).glob("*/*.idl"))
    assert len(sources) == len(bundled) > 0
    for src in sources:
        ours = bundle_dir() / pkg_dir.name / src.parent.name / f"{src.stem}.idl"
        assert tool.to_idl(src, pkg_dir.name) == ours.read_text(encoding="utf-8"), ours


def _structs(text: str) -> dict[str, MessageType]:
    return {k: dataclasses.replace(v, source="") for k, v in parse_idl(text).structs.items()}


@pytest.mark.interop
def test_pypi_packages_give_the_bundle_structs(jazzy_share: Path) -> None:
    tool = _tool()
    compared = 0
    for pkg_dir in sorted(bundle_dir().iterdir()):
        official = jazzy_share / pkg_dir.name
        if pkg_dir.name.startswith("_") or not official.is_dir():
            continue
        for src in _sources(official):
            ours = pkg_dir / src.parent.name / f"{src.stem}.idl"
            assert _structs(tool.to_idl(src, pkg_dir.name)) == \
                _structs(ours.read_text(encoding="utf-8")), ours
            compared += 1
    assert compared >= 199  # every interface of the PyPI packages


DISTRO_FILES = DATA / "interfaces_distro"


def _wire(text: str) -> dict[str, MessageType]:
    """Structs without constants: what a distro override is for (idl/README.md)."""
    return {k: dataclasses.replace(v, constants=()) for k, v in _structs(text).items()}


@pytest.mark.offline
@pytest.mark.parametrize("distro", ["humble", "kilted"])
def test_distro_overrides_are_the_official_files_where_the_wire_differs(distro: str) -> None:
    tool, overridden = _tool(), 0
    for pkg_dir in sorted((DISTRO_FILES / distro).iterdir()):
        for src in _sources(pkg_dir):
            rel = Path(pkg_dir.name, src.parent.name, f"{src.stem}.idl")
            theirs = tool.to_idl(src, pkg_dir.name)
            override = bundle_dir() / "_distro" / distro / rel
            jazzy = bundle_dir() / rel
            if override.exists():
                assert theirs == override.read_text(encoding="utf-8"), override
                overridden += 1
                if jazzy.exists():  # else new in that distro
                    assert _wire(theirs) != _wire(jazzy.read_text(encoding="utf-8")), rel
            else:
                assert _wire(theirs) == _wire(jazzy.read_text(encoding="utf-8")), rel
    packages = [p.name for p in (DISTRO_FILES / distro).iterdir()]
    assert overridden == sum(
        len(list((bundle_dir() / "_distro" / distro / p).glob("*/*.idl"))) for p in packages)
