#!/usr/bin/env bash
# Runs today's code on the suite as it was at COMMIT, the way scripts/test.sh runs the suite
# (scripts/pytest_phases.sh: same two phases, markers and workers, in the test network
# namespace), and prints each phase's wall time: "the suite as of issue N" timed on today's code.
#   CI=true scripts/suite_as_of.sh 599eb3c [pytest args...]
# Needs what scripts/test.sh set up (.venv, .cache); builds this tree's wheel as it does.
# COMMIT's node ids are collected once from its own sources (cached in .cache/suite-as-of/).
# An id kept today runs as is; one whose file moved runs under its new file when its
# Class::test[params] is unique today; the rest (renamed or dropped) are listed as gone.
set -uo pipefail
cd "$(dirname "$0")/.."
[ $# -ge 1 ] || { echo "usage: $0 COMMIT [pytest args...]" >&2; exit 2; }
PY=${RCAN_RTPS_TEST_PYTHON:-.venv/bin/python}
[[ $PY = /* ]] || PY=$PWD/$PY
sha=$(git rev-parse --verify "$1^{commit}") || exit 2
shift
cache=$PWD/.cache/suite-as-of
tmp=$(mktemp -d)
trap 'rm -rf "$tmp"' EXIT
mkdir -p "$cache"

# pytest's node ids, one a line; its last line ("N tests collected[, M errors]") to stderr
node_ids() {
  "$PY" -m pytest --collect-only -q -p no:cacheprovider "$@" >"$tmp/collect.log"
  grep -v '^$' "$tmp/collect.log" | tail -n 1 >&2
  grep -E '^[^ ]+\.py::' "$tmp/collect.log"
}

if [ ! -s "$cache/$sha.ids" ]; then
  echo "-- collecting the suite at ${sha:0:7} from its own sources"
  mkdir "$tmp/old" && git archive "$sha" | tar -x -C "$tmp/old"
  ln -s "$PWD/.cache" "$tmp/old/.cache"
  (cd "$tmp/old" && PYTHONPATH="$tmp/old/src" node_ids --continue-on-collection-errors) \
    >"$tmp/old.ids" || { echo "no tests collected at ${sha:0:7}" >&2; exit 1; }
  mv "$tmp/old.ids" "$cache/$sha.ids"
fi

node_ids >"$tmp/today.ids" || { echo "no tests collected today" >&2; exit 1; }
run=$tmp/run.ids
: >"$tmp/gone.ids"
awk -v gone="$tmp/gone.ids" '
  function key(id) { return substr(id, index(id, "::")) }
  NR == FNR { today[$0] = 1; n[key($0)]++; by[key($0)] = $0; next }
  $0 in today { if (!seen[$0]++) print; same++; next }
  n[key($0)] == 1 { if (!seen[by[key($0)]]++) print by[key($0)]; moved++; next }
  { print > gone; lost++ }
  END { printf "-- %d ids at the commit: %d run as is, %d in a moved file, %d gone\n",
          FNR, same, moved, lost > "/dev/stderr" }' "$tmp/today.ids" "$cache/$sha.ids" >"$run"
sed 's/^/   gone: /' "$tmp/gone.ids"

if [ -z "${RCAN_RTPS_WHEEL_DIR:-}" ]; then  # the packaging tests install this tree's wheel
  export RCAN_RTPS_WHEEL_DIR=$tmp/dist
  "$PY" -m pip wheel -q --no-deps -w "$RCAN_RTPS_WHEEL_DIR" . >"$tmp/wheel.log" 2>&1 ||
    { cat "$tmp/wheel.log" >&2; exit 1; }
fi

# In the test network namespace as scripts/test.sh enters it, else loopback discovery only
phases=(bash scripts/pytest_phases.sh "@$run" "$@")
if [ "$(uname -s)" = Linux ] && [ "$(id -u)" = 0 ] && [ -z "${RCAN_RTPS_IN_NETNS:-}" ]; then
  phases=(scripts/netns "${phases[@]}")
else
  export ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST
fi
"${phases[@]}" | {
  results=()
  while IFS= read -r line; do
    printf '%s\n' "$line"
    case $line in
      "-- phase 1"*) t1=$SECONDS ;;
      "-- phase 2"*) t2=$SECONDS ;;
      "="*" in "*[0-9]s*"=") read -r r <<<"${line//=}"; results+=("$r") ;;
    esac
  done
  t3=$SECONDS
  echo "-- the suite at ${sha:0:7} on $(git rev-parse --short HEAD): phase 1 $((t2 - t1)) s," \
       "phase 2 $((t3 - t2)) s, total $((t3 - t1)) s"
  printf -- '-- %s\n' "${results[@]}"
}
exit "${PIPESTATUS[0]}"
