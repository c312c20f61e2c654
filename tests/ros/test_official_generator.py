"""Bundle packages not on PyPI against the official ROS 2 Jazzy generator, run live.

The official `.msg`/`.srv`/`.action` files (tests/data/interfaces/, from each package's
Jazzy branch or tag) go through `rosidl_adapter` and `rosidl_generator_type_description` in
the oracle environment (tests/data/make_rihs01_official.py). Every RIHS01 hash they give
must equal what our hasher computes from our bundle IDL, and the IDL `rosidl_adapter` writes
must read back, through our parser, as exactly our structs: the same fields, and also the
constants and defaults, which the hash does not cover.
"""

from __future__ import annotations

import dataclasses
import json
import subprocess
from pathlib import Path

import pytest

from rcan_rtps.ros.typesys.idl_parser import parse_idl
from rcan_rtps.ros.typesys.model import MessageType
from rcan_rtps.ros.typesys.store import TypeStore, bundle_dir

from .offline_data import DATA

pytestmark = pytest.mark.interop
SCRIPT = DATA / "make_rihs01_official.py"
PACKAGES = sorted(p.name for p in (DATA / "interfaces").iterdir() if p.is_dir())


@dataclasses.dataclass
class Official:
    hashes: dict[str, str]
    idl: Path  # rosidl_adapter's IDL, laid out like the bundle


@pytest.fixture(scope="module")
def official(jazzy_python: Path, tmp_path_factory: pytest.TempPathFactory) -> Official:
    tmp = tmp_path_factory.mktemp("official")
    subprocess.run(
        [str(jazzy_python), str(SCRIPT), "--out", str(tmp / "h.json"),
         "--idl-out", str(tmp / "idl")],
        check=True, capture_output=True, text=True, timeout=300)
    hashes = json.loads((tmp / "h.json").read_text(encoding="utf-8"))["hashes"]
    return Official(hashes, tmp / "idl")


def wrong_hashes(store: TypeStore, expected: dict[str, str]) -> list[str]:
    return [f"{name}: ours {store.hash_of(name)} != official {want}"
            for name, want in expected.items() if store.hash_of(name) != want]


def test_every_hash_equals_the_official_generators(official: Official) -> None:
    store = TypeStore(distro="jazzy")
    assert wrong_hashes(store, official.hashes) == []
    # every bundle interface of these packages was hashed, and nothing else
    bundle = {n for n in store.interface_names() if n.split("/")[0] in PACKAGES}
    assert {n for n in bundle if n in official.hashes} == bundle
    assert {n.split("/")[0] for n in official.hashes} == set(PACKAGES)
    assert len(official.hashes) > 500


def _structs(path: Path) -> dict[str, MessageType]:
    parsed = parse_idl(path.read_text(encoding="utf-8"), str(path))
    return {k: dataclasses.replace(v, source="") for k, v in parsed.structs.items()}


def test_adapter_idl_reads_as_our_structs_with_constants_and_defaults(official: Official) -> None:
    compared = 0
    for theirs in sorted(official.idl.glob("*/*/*.idl")):
        ours = bundle_dir() / theirs.relative_to(official.idl)
        assert _structs(ours) == _structs(theirs), ours
        compared += 1
    assert compared == sum(len(list((bundle_dir() / p).glob("*/*.idl"))) for p in PACKAGES)


def test_a_wrong_field_in_our_idl_is_caught(official: Official, tmp_path: Path) -> None:
    """TFMessage with `Transform` where Jazzy has `TransformStamped`: the hashes must differ."""
    source = bundle_dir() / "tf2_msgs/msg/TFMessage.idl"
    text = source.read_text(encoding="utf-8")
    broken = text.replace("msg::TransformStamped>", "msg::Transform>").replace(
        "TransformStamped.idl", "Transform.idl")
    assert broken != text
    (tmp_path / "tf2_msgs/msg").mkdir(parents=True)
    (tmp_path / "tf2_msgs/msg/TFMessage.idl").write_text(broken, encoding="utf-8")
    wrong = wrong_hashes(TypeStore([tmp_path], distro="jazzy"), official.hashes)
    assert any(w.startswith("tf2_msgs/msg/TFMessage:") for w in wrong)
