# Set-up helpers of scripts/test.sh (sourced; also sourced by a test of their failure paths).

PY=${PYTHON:-python3.11}
command -v "$PY" >/dev/null 2>&1 || PY=python3

# Runs pip quietly (its location warnings hidden) and fails exactly when pip fails.
quiet_pip() {
  local out status=0
  out=$("$@" 2>&1) || status=$?
  printf '%s\n' "$out" | grep -v -e '^WARNING: Location' -e '^\s*$' || true
  return "$status"
}

# Installs a virtualenv once per requirement set; the stamp file makes reruns cheap. A failed
# install leaves no stamp (and no half-made venv), so the next run installs again.
ensure_venv() {  # dir stamp-text pip-args...
  local dir=$1 stamp=$2; shift 2
  if [ -f "$dir/.stamp" ] && [ "$(cat "$dir/.stamp")" = "$stamp" ]; then return 0; fi
  rm -rf "$dir"
  "$PY" -m venv "$dir" || { rm -rf "$dir"; return 1; }
  quiet_pip "$dir/bin/pip" install -q "$@" || {
    echo "pip install into $dir failed" >&2; rm -rf "$dir"; return 1; }
  "$dir/bin/python" -c 'import sys; sys.exit(0)' || { rm -rf "$dir"; return 1; }
  echo "$stamp" > "$dir/.stamp"
}
