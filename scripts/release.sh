#!/usr/bin/env bash
# Builds and checks a release of rcan-rtps (docs/release.md).
#   scripts/release.sh [DIST]        build the sdist and wheel into DIST (default dist/), check
#                                    them, install the wheel in a fresh venv and run the tour
#   scripts/release.sh check DIR     check the wheel (and sdist, if there) in DIR: metadata
#                                    and contents (tests/test_packaging.py runs this)
#   scripts/release.sh smoke WHEEL   install WHEEL in a fresh venv; `run --sim` reaches its
#                                    ready line, /api/status answers, a move executes
# The build tools (build, twine) go into .cache/release-tools when missing. The smoke's bridge
# runs in a private network namespace (scripts/netns) when root on Linux, else on loopback.
set -euo pipefail
root="$(cd "$(dirname "$0")/.." && pwd)"
# shellcheck source=scripts/setup_lib.sh
. "$root/scripts/setup_lib.sh"

version() {  # the version the tree says, in both places it says it
  local in_toml in_init
  in_toml=$(sed -n 's/^version = "\(.*\)"$/\1/p' "$root/pyproject.toml")
  in_init=$(sed -n 's/^__version__ = "\(.*\)"$/\1/p' "$root/src/rcan_rtps/__init__.py")
  [ -n "$in_toml" ] && [ "$in_toml" = "$in_init" ] || {
    echo "pyproject.toml says ${in_toml:-nothing}, rcan_rtps.__version__ ${in_init:-nothing}" >&2
    return 1; }
  echo "$in_toml"
}

build() {  # dist-dir
  local dist=$1 tools="$root/.cache/release-tools"
  ensure_venv "$tools" "build twine" build twine \
    || { echo "could not install the build tools (build, twine)" >&2; return 1; }
  rm -rf "$dist" && mkdir -p "$dist"
  "$tools/bin/python" -m build --sdist --wheel --outdir "$dist" "$root" >"$dist/.build.log" 2>&1 \
    || { cat "$dist/.build.log" >&2; echo "python -m build failed" >&2; return 1; }
  rm -f "$dist/.build.log"
  "$tools/bin/twine" check --strict "$dist"/*
}

check() {  # dir: metadata and contents of the built artifacts
  local dir=$1 expected
  expected=$(version)
  "$PY" - "$root" "$dir" "$expected" <<'PYCHECK'
import email.parser, re, sys, tarfile, tomllib, zipfile
from pathlib import Path

root, dist, version = Path(sys.argv[1]), Path(sys.argv[2]), sys.argv[3]
problems = []
project = tomllib.loads((root / "pyproject.toml").read_text())["project"]


def norm(requirement):  # 'prometheus_client>=0.20' and 'prometheus-client>=0.20' alike
    name, rest = re.match(r"([A-Za-z0-9._-]+)(.*)", re.sub(r"\s+", "", requirement.split(";")[0])).groups()
    return re.sub(r"[._-]+", "-", name.lower()), tuple(sorted(filter(None, rest.split(","))))


wheels = sorted(dist.glob("rcan_rtps-*.whl"))
if [w.name for w in wheels] != [f"rcan_rtps-{version}-py3-none-any.whl"]:
    sys.exit(f"expected one rcan_rtps-{version}-py3-none-any.whl in {dist}, found "
             f"{[w.name for w in wheels] or 'none'}")
wheel = zipfile.ZipFile(wheels[0])
names = set(wheel.namelist())
info = f"rcan_rtps-{version}.dist-info"
meta = email.parser.Parser().parsestr(wheel.read(f"{info}/METADATA").decode())
for field, want in (("Name", "rcan-rtps"), ("Version", version),
                    ("Requires-Python", project["requires-python"]),
                    ("Description-Content-Type", "text/markdown")):
    if meta.get(field) != want:
        problems.append(f"METADATA {field}: {meta.get(field)!r}, expected {want!r}")
if project["license"] not in (meta.get("License-Expression"), meta.get("License")):
    problems.append(f"METADATA has no license {project['license']}")
if not (meta.get("Summary") or "").strip():
    problems.append("METADATA has no Summary")
if "## A 60-second tour" not in (meta.get_payload() or ""):
    problems.append("METADATA's description is not the README")
requires = {norm(r) for r in meta.get_all("Requires-Dist") or [] if "extra ==" not in r}
if requires != {norm(r) for r in project["dependencies"]}:
    problems.append(f"Requires-Dist {sorted(requires)} differs from pyproject's dependencies")
extras = set(meta.get_all("Provides-Extra") or [])
if extras != set(project["optional-dependencies"]):
    problems.append(f"Provides-Extra {sorted(extras)}, expected "
                    f"{sorted(project['optional-dependencies'])}")
entry = wheel.read(f"{info}/entry_points.txt").decode()
if "rcan-rtps = rcan_rtps._launch:main" not in entry:
    problems.append("no rcan-rtps console script")

src = root / "src"
modules = {p.relative_to(src).as_posix() for p in (src / "rcan_rtps").rglob("*.py")}
wheel_modules = {n for n in names if n.endswith(".py")}
if modules - wheel_modules:
    problems.append(f"modules missing from the wheel: {sorted(modules - wheel_modules)}")
if wheel_modules - modules:
    problems.append(f"modules in the wheel that the tree does not have (a stale build?): "
                    f"{sorted(wheel_modules - modules)}")
wanted = {"rcan_rtps/py.typed"}
wanted |= {f"rcan_rtps/console/static/{p.name}"
           for p in (src / "rcan_rtps/console/static").iterdir()}
wanted |= {f"rcan_rtps/conformance/{p.name}"  # the vendored RCAN conformance suite
           for p in (src / "rcan_rtps/conformance").glob("*.json")}
wanted |= {f"rcan_rtps/_idl/{p.relative_to(root / 'idl').as_posix()}"
           for p in (root / "idl").rglob("*.idl")}
if wanted - names:
    problems.append(f"files missing from the wheel: {sorted(wanted - names)[:10]}")
stray = sorted(n for n in names if n.startswith(("tests/", "bench/", "scripts/"))
               or re.search(r"(^|/)(\.cache|\.venv|__pycache__|\.git)/|\.pyc$", n))
if stray:
    problems.append(f"files that do not belong in the wheel: {stray[:10]}")
print(f"wheel {wheels[0].name}: {len(names)} files, metadata and contents checked")

for sdist_path in sorted(dist.glob("rcan_rtps-*.tar.gz")):
    if sdist_path.name != f"rcan_rtps-{version}.tar.gz":
        problems.append(f"sdist {sdist_path.name}, expected rcan_rtps-{version}.tar.gz")
        continue
    with tarfile.open(sdist_path) as sdist:
        members = {m.name.split("/", 1)[1] for m in sdist.getmembers() if "/" in m.name}
    need = {"PKG-INFO", "pyproject.toml", "README.md", "src/rcan_rtps/__init__.py",
            "src/rcan_rtps/console/static/index.html", "idl/std_msgs/msg/Header.idl"}
    if need - members:
        problems.append(f"sdist lacks {sorted(need - members)}")
    stray = sorted(m for m in members
                   if re.search(r"(^|/)(\.cache|\.venv|__pycache__|\.git)(/|$)", m))
    if stray:
        problems.append(f"sdist carries {stray[:10]}")
    print(f"sdist {sdist_path.name}: {len(members)} entries checked")

if problems:
    sys.exit("release check failed:\n  " + "\n  ".join(problems))
PYCHECK
}

smoke() {  # wheel: a fresh venv, then the README tour's core against run --sim
  local wheel work
  wheel=$(cd "$(dirname "$1")" && pwd)/$(basename "$1")
  work=$(mktemp -d)
  trap 'rm -rf "$work"' RETURN
  "$PY" -m venv "$work/venv"
  quiet_pip "$work/venv/bin/pip" install -q "$wheel" \
    || { echo "the wheel does not install in a fresh venv" >&2; return 1; }
  local runner=(bash -c "$(declare -f tour); tour \"\$@\"" tour "$work")
  if [ "$(uname -s)" = Linux ] && [ "$(id -u)" = 0 ]; then
    "$root/scripts/netns" "${runner[@]}"
  else
    port_free 8765 || return 1
    "${runner[@]}"
  fi
}

tour() {  # work-dir (its venv has rcan-rtps): ready line, status, a move; a clean stop
  local work=$1 api=http://127.0.0.1:8765 pid status=0
  export XDG_STATE_HOME="$work/state" RCAN_BRIDGE_TOKEN=release-smoke-owner \
    RCAN_DEMO_USER_TOKEN=release-smoke-user
  cd "$work"
  "$work/venv/bin/rcan-rtps" run --sim >"$work/out" 2>&1 &
  pid=$!
  for _ in $(seq 1 240); do
    grep -q '^rcan-rtps ready api=' "$work/out" && break
    kill -0 "$pid" 2>/dev/null || { cat "$work/out"; echo "run --sim exited early" >&2; return 1; }
    sleep 0.5
  done
  grep -q '^rcan-rtps ready api=' "$work/out" \
    || { cat "$work/out"; kill "$pid"; echo "no ready line" >&2; return 1; }
  local status_body
  status_body=$(curl -s -w ' %{http_code}' -H "Authorization: Bearer $RCAN_BRIDGE_TOKEN" \
    "$api/api/status")
  case "$status_body" in
    *'"connected":true'*' 200') ;;
    *) kill -INT "$pid"; echo "/api/status did not report the robot connected: $status_body" >&2
       return 1 ;;
  esac
  local moved
  moved=$(curl -s -w ' %{http_code}' -H "Authorization: Bearer $RCAN_DEMO_USER_TOKEN" \
    -H 'Content-Type: application/json' \
    -d '{"action": "move", "params": {"linear_x": 0.3, "duration_s": 1}}' "$api/api/command")
  case "$moved" in
    *'"executed"'*' 200') ;;
    *) kill -INT "$pid"; echo "the move was not executed: $moved" >&2; return 1 ;;
  esac
  kill -INT "$pid"
  wait "$pid" || status=$?
  [ "$status" -eq 0 ] || { cat "$work/out"; echo "run --sim exited $status on SIGINT" >&2; return 1; }
  echo "smoke: ready, /api/status answered, a move executed, stopped cleanly"
}

case "${1:-}" in
  check) [ $# -eq 2 ] || { echo "usage: $0 check DIR" >&2; exit 2; }; check "$2" ;;
  smoke) [ $# -eq 2 ] || { echo "usage: $0 smoke WHEEL" >&2; exit 2; }; smoke "$2" ;;
  -h|--help) sed -n '2,11p' "$0" ;;
  *)
    dist=$(mkdir -p "${1:-$root/dist}" && cd "${1:-$root/dist}" && pwd)
    build "$dist"
    check "$dist"
    smoke "$(ls "$dist"/rcan_rtps-*.whl)"
    echo "release $(version): $(cd "$dist" && ls | tr '\n' ' ')built and checked"
    ;;
esac
