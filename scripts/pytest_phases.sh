#!/usr/bin/env bash
# Runs the test suite in two phases (scripts/test.sh calls it, inside the test network
# namespace when there is one); extra arguments go to both pytest runs:
#   1. every test not marked `serial`, spread over pytest-xdist workers (RCAN_RTPS_TEST_WORKERS,
#      default: 2 per core), an idle worker taking tests queued for a busy one (worksteal).
#      Each worker has its own DDS domains and temporary directories (tests/conftest.py).
#   2. the `serial` tests, alone: a CPU load generator would starve (and be disturbed by)
#      tests beside it; mDNS adverts share one multicast group and the demo's name; bag
#      playback's arrival gaps would carry the other workers' scheduling delays.
# Not `--dist loadgroup` with `xdist_group` marks: on pytest 9.2 xdist 3.8 silently stops
# grouping (pytest-xdist issue 1386), so what must not overlap runs in phase 2.
# RCAN_RTPS_TEST_WORKERS=0 runs phase 1 in one process, like plain pytest. A `-m` among the
# arguments replaces the phase's own (pytest keeps the last one).
# Exit status: the first phase's failure, else the second's; "no tests selected" (5) in one
# phase is fine when the other ran tests.
set -uo pipefail
cd "$(dirname "$0")/.."
PY=${RCAN_RTPS_TEST_PYTHON:-.venv/bin/python}
workers=${RCAN_RTPS_TEST_WORKERS:-$(( 2 * $(nproc 2>/dev/null || echo 1) ))}

# The namespace's UDP counters after each phase (cumulative): a loss in a test is then told from a datagram
# the kernel dropped (RcvbufErrors) or not (docs/design/zero-loss.md).
udp_counters() {
  [ -n "${RCAN_RTPS_IN_NETNS:-}" ] && [ -r /proc/net/snmp ] &&
    echo "-- UDP counters of the test network namespace: $(grep '^Udp:' /proc/net/snmp |
      awk 'NR==1{for(i=2;i<=NF;i++)h[i]=$i} NR==2{for(i=2;i<=NF;i++)printf "%s=%s ", h[i], $i}')"
  return 0
}

echo "-- phase 1: in parallel ($workers workers), all but the serial tests"
"$PY" -m pytest -n "$workers" --dist worksteal -m "not serial" "$@"
first=$?
udp_counters
echo "-- phase 2: the serial tests, alone"
"$PY" -m pytest -n 0 -m serial "$@"
second=$?
udp_counters

if [ "$first" -eq 5 ] && [ "$second" -eq 5 ]; then exit 5; fi
[ "$first" -eq 5 ] && first=0
[ "$second" -eq 5 ] && second=0
[ "$first" -ne 0 ] && exit "$first"
exit "$second"
