#!/usr/bin/env bash
# Runs README.md's main command verbatim in a fresh copy, waits for the ready line, and
# stops it with SIGINT (it must exit 0). It runs outside a network namespace because its
# `pip install` needs the package registries; the demo itself keeps DDS and mDNS on loopback
# (localhost-only discovery) and serves 127.0.0.1:8765, which must be free.
set -euo pipefail
root="$(cd "$(dirname "$0")/.." && pwd)"
# shellcheck source=scripts/setup_lib.sh
. "$root/scripts/setup_lib.sh"
cmd=$(awk '/<!-- main-command -->/{f=1; next} f && /^```bash/{g=1; next} g && /^```/{exit} g' \
      "$root/README.md")
[ -n "$cmd" ] || { echo "README.md has no main command block" >&2; exit 1; }
work=$(mktemp -d)
trap 'rm -rf "$work"' EXIT
port_free 8765 || { echo "the README's demo serves on 8765: free it first" >&2; exit 1; }
copy_source "$root" "$work/r"
cd "$work/r"
export XDG_STATE_HOME="$work/state" RCAN_BRIDGE_TOKEN=readme-check-owner-token
setsid bash -c "$cmd" > "$work/out" 2>&1 &
pid=$!
for _ in $(seq 1 600); do
  grep -q '^rcan-rtps ready api=' "$work/out" && break
  kill -0 "$pid" 2>/dev/null || { cat "$work/out"; echo "main command exited early" >&2; exit 1; }
  sleep 0.5
done
grep -q '^rcan-rtps ready api=' "$work/out" || { cat "$work/out"; echo "no ready line" >&2; exit 1; }
curl -sf -H "Authorization: Bearer $RCAN_BRIDGE_TOKEN" http://127.0.0.1:8765/api/status >/dev/null \
  || { echo "the API did not answer" >&2; kill -INT -- -"$pid"; exit 1; }
kill -INT -- -"$pid"
status=0; wait "$pid" || status=$?
[ "$status" -eq 0 ] || { cat "$work/out"; echo "main command exited $status on SIGINT" >&2; exit 1; }
echo "README main command: ready, answered, stopped cleanly"
