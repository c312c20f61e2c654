"""The wheel built from this repo carries the IDL bundle and works outside the source tree."""

from __future__ import annotations

import os
import subprocess
import sys
import zipfile
from pathlib import Path

import pytest

import rcan_rtps

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def wheel() -> Path:
    wheel_dir = Path(os.environ.get("RCAN_RTPS_WHEEL_DIR", ROOT / ".cache" / "dist"))
    wheels = sorted(wheel_dir.glob("rcan_rtps-*.whl"))
    if not wheels:
        if os.environ.get("CI"):
            pytest.fail("no wheel was built: scripts/test.sh builds it before the tests")
        pytest.skip("no wheel built; run scripts/test.sh")
    stale = _differing_sources(wheels[-1])
    if stale:  # built from another state of the tree: its results would not be this tree's
        why = f"{wheels[-1].name} is stale: {len(stale)} module(s) differ from src/ ({stale[0]})"
        if os.environ.get("CI"):
            pytest.fail(why)
        pytest.skip(f"{why}; run scripts/test.sh")
    return wheels[-1]


def _differing_sources(wheel: Path) -> list[str]:
    """The Python modules of the package whose bytes in `wheel` are not those under src/
    (or that one side lacks)."""
    src = ROOT / "src"
    with zipfile.ZipFile(wheel) as archive:
        packed = {n: archive.read(n) for n in archive.namelist()
                  if n.startswith("rcan_rtps/") and n.endswith(".py")}
    here = {p.relative_to(src).as_posix(): p.read_bytes()
            for p in (src / "rcan_rtps").rglob("*.py")}
    return sorted(n for n in packed.keys() | here.keys() if packed.get(n) != here.get(n))


def test_wheel_carries_the_idl_bundle(wheel: Path) -> None:
    names = set(zipfile.ZipFile(wheel).namelist())
    bundle = {n for n in names if n.startswith("rcan_rtps/_idl/") and n.endswith(".idl")}
    shipped = {p.relative_to(ROOT / "idl").as_posix() for p in (ROOT / "idl").rglob("*.idl")}
    assert {n.removeprefix("rcan_rtps/_idl/") for n in bundle} == shipped
    assert "rcan_rtps/py.typed" in names
    # the operator console's static files (served from the installed package, no build step)
    static = ROOT / "src" / "rcan_rtps" / "console" / "static"
    shipped_console = {f"rcan_rtps/console/static/{p.name}" for p in static.iterdir()}
    assert shipped_console and shipped_console <= names
    assert any(n.endswith("entry_points.txt") for n in names)


def test_installed_wheel_works_outside_the_tree(wheel: Path, tmp_path: Path) -> None:
    target = tmp_path / "site"
    subprocess.run([sys.executable, "-m", "pip", "install", "-q", "--no-deps", "--no-index",
                    "--target", str(target), str(wheel)], check=True, capture_output=True)
    env = {**os.environ, "PYTHONPATH": str(target)}
    probe = ("import rcan_rtps, sys; from rcan_rtps.ros.typesys.store import bundle_dir; "
             "print(rcan_rtps.__file__); print(bundle_dir())")
    done = subprocess.run([sys.executable, "-c", probe], env=env, cwd=tmp_path,
                          capture_output=True, text=True, check=True)
    module_file, bundle = done.stdout.split()
    assert module_file.startswith(str(target)) and bundle.startswith(str(target))
    hashed = subprocess.run([sys.executable, "-m", "rcan_rtps", "interface", "hash",
                             "geometry_msgs/msg/Twist"], env=env, cwd=tmp_path,
                            capture_output=True, text=True)
    assert hashed.returncode == 0, hashed.stderr
    assert hashed.stdout.startswith("RIHS01_") and len(hashed.stdout.strip()) == 71
    console = subprocess.run(  # the console's files, read from the installed package
        [sys.executable, "-c", "import rcan_rtps.console as c; print(c.__file__); "
         "print(b'<title>rcan-rtps console</title>' in c.asset('index.html'))"],
        env=env, cwd=tmp_path, capture_output=True, text=True, check=True)
    assert console.stdout.split() == [str(target / "rcan_rtps" / "console" / "__init__.py"),
                                      "True"]
    assert rcan_rtps.__version__ in subprocess.run(
        [sys.executable, "-m", "rcan_rtps", "--version"], env=env, cwd=tmp_path,
        capture_output=True, text=True).stdout


def _release_check(directory: Path) -> subprocess.CompletedProcess[str]:
    return subprocess.run(["bash", str(ROOT / "scripts" / "release.sh"), "check",
                           str(directory)], capture_output=True, text=True, timeout=120)


def test_the_release_check_passes_the_built_wheel(wheel: Path) -> None:
    done = _release_check(wheel.parent)
    assert done.returncode == 0, done.stdout + done.stderr
    assert f"wheel {wheel.name}: " in done.stdout and "metadata and contents checked" in done.stdout


def test_the_release_check_refuses_a_wheel_with_tests_and_without_the_console(
        wheel: Path, tmp_path: Path) -> None:
    bad = tmp_path / wheel.name
    with zipfile.ZipFile(wheel) as good, zipfile.ZipFile(bad, "w") as out:
        for item in good.infolist():
            if item.filename != "rcan_rtps/console/static/index.html":
                out.writestr(item, good.read(item))
        out.writestr("tests/conftest.py", "")
        out.writestr("rcan_rtps/.cache/dist/x", "")
    done = _release_check(tmp_path)
    assert done.returncode == 1
    assert "files missing from the wheel: ['rcan_rtps/console/static/index.html']" in done.stderr
    assert ("files that do not belong in the wheel: ['rcan_rtps/.cache/dist/x', "
            "'tests/conftest.py']") in done.stderr
