#!/usr/bin/env bash
# The product on the oldest Python it promises (requires-python >= 3.10: a Jetson's Ubuntu
# 22.04 has 3.10), as scripts/test.sh checks it; the rest of the suite runs on .venv's 3.11.
#   scripts/python310.sh prepare WHEEL  .cache/venv-py310: WHEEL and its `test` extra on a 3.10
#                                       interpreter (network; the venv is reused while
#                                       pyproject.toml and the interpreter are unchanged, the
#                                       wheel reinstalled every time)
#   scripts/python310.sh test [ARGS]    the part of the suite below, on that venv, against the
#                                       installed wheel (never src/); extra arguments go to
#                                       pytest. Speaks DDS: run it inside scripts/netns.
#   scripts/python310.sh find           which interpreter: $PYTHON310, else python3.10 on PATH,
#                                       else pyenv's newest 3.10 ($PYENV_ROOT, by default
#                                       ~/.pyenv: /root/.pyenv/versions/3.10.* here)
# Without a 3.10 interpreter, prepare and test exit 3 saying the tests are skipped, or under
# CI=true fail (exit 1): there the 3.10 tests must run; find exits 3.
set -uo pipefail
repo=$(cd "$(dirname "$0")/.." && pwd)
venv=$repo/.cache/venv-py310
NO_PYTHON310=3

# What runs on 3.10: tests that need no DDS and are cheap (the governance kernel, RCAN
# messages, config loading, the packaging and public-API checks); the tests of the code that
# differs on 3.10 (the event loop a run uses, an HTTP body's deadline, the MCP server's
# exception groups); and the installed wheel's `rcan-rtps run --sim` (a move, an e-stop, a
# clean stop). `slow` and `serial` tests stay on 3.11. 1 to 2.5 minutes on 2 busy cores.
TESTS=(
  tests/governance tests/rcan tests/config tests/test_packaging.py tests/test_public_api.py
  tests/cli/test_event_loop.py tests/api/test_deadlines.py tests/mcp/test_mcp_signals.py
  tests/interop/test_console_script_run.py
)

say() { printf 'python3.10: %s\n' "$*"; }

# No interpreter (find_python310 said where it looked): a skip, but not under CI=true.
no_python310() {
  if [ "${CI:-}" = true ]; then
    say "under CI=true the Python 3.10 tests must run: failing" >&2
    exit 1
  fi
  say "SKIPPED: the Python 3.10 tests do not run here (PYTHON310 names an interpreter)"
  exit "$NO_PYTHON310"
}

is_python310() {  # a command that runs and is CPython 3.10 with venv
  "$1" -c 'import sys, venv, ensurepip; sys.exit(sys.version_info[:2] != (3, 10))' \
    >/dev/null 2>&1
}

# Prints the interpreter to use, or says why there is none and returns 1.
find_python310() {
  if [ -n "${PYTHON310:-}" ]; then  # named: used or refused, never passed over
    is_python310 "$PYTHON310" && { command -v "$PYTHON310"; return 0; }
    say "PYTHON310=$PYTHON310 is not a Python 3.10 with venv" >&2
    return 1
  fi
  local candidate versions=${PYENV_ROOT:-$HOME/.pyenv}/versions
  # pyenv's shim is on PATH but runs only when 3.10 is pyenv's selected version: tried, not
  # trusted; the interpreters themselves are then taken from its folder, newest first
  while IFS= read -r candidate; do
    is_python310 "$candidate" && { command -v "$candidate"; return 0; }
  done < <(echo python3.10; printf '%s\n' "$versions"/3.10.*/bin/python3.10 | sort -rV)
  say "no Python 3.10 interpreter: none in PYTHON310, python3.10 on PATH or" \
    "$versions/3.10.*" >&2
  return 1
}

prepare() {  # wheel
  local wheel=${1:?prepare WHEEL} python
  [ -f "$wheel" ] || { say "no wheel at $wheel" >&2; return 1; }
  python=$(find_python310) || no_python310
  # shellcheck source=scripts/setup_lib.sh
  . "$repo/scripts/setup_lib.sh"
  local stamp
  stamp="$python $("$python" -VV | head -1):$(sha256sum "$repo/pyproject.toml" | cut -c1-16)"
  PY=$python ensure_venv "$venv" "$stamp" "${wheel}[test]" \
    || { say "could not install $(basename "$wheel") with its test extra" >&2; return 1; }
  quiet_pip "$venv/bin/pip" install -q --no-deps --force-reinstall "$wheel" \
    || { say "could not reinstall $(basename "$wheel")" >&2; return 1; }
  say "$("$venv/bin/python" -V) in .cache/venv-py310, $(basename "$wheel") installed"
}

run_tests() {  # pytest-args...
  find_python310 >/dev/null || no_python310
  [ -x "$venv/bin/python" ] || { say "no .cache/venv-py310: run prepare first" >&2; return 1; }
  cd "$repo" || return 1
  # the installed wheel, not the tree: tests/conftest.py refuses a rcan_rtps from src/
  unset PYTHONPATH
  RCAN_RTPS_TEST_INSTALLED=1 "$venv/bin/python" -m pytest -p no:cacheprovider \
    -n "${RCAN_RTPS_TEST_WORKERS:-2}" --dist worksteal -m "not slow and not serial" \
    "${TESTS[@]}" "$@"
}

case "${1:-}" in
  prepare) shift; prepare "$@" ;;
  test) shift; run_tests "$@" ;;
  find) find_python310 || exit "$NO_PYTHON310" ;;
  *) echo "usage: $0 find | prepare WHEEL | test [PYTEST-ARGS]" >&2; exit 2 ;;
esac
