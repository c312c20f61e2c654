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

# Copies the source tree to DEST: the files git tracks in a checkout; elsewhere (an sdist, a
# plain copy) everything but version control, environments and caches.
copy_source() {  # src dest
  local src=$1 dest=$2
  mkdir -p "$dest"
  if git -C "$src" rev-parse --is-inside-work-tree >/dev/null 2>&1; then
    git -C "$src" ls-files -z | (cd "$src" && tar --null -T - -cf -) | tar -C "$dest" -xf -
  else
    (cd "$src" && tar --exclude=./.git --exclude=./.venv --exclude=./.cache \
      --exclude='*.egg-info' --exclude=__pycache__ -cf - .) | tar -C "$dest" -xf -
  fi
}

# Fails (with the reason) when something on this machine already listens on a local TCP port.
port_free() {  # port
  if (exec 3<>"/dev/tcp/127.0.0.1/$1") 2>/dev/null; then
    echo "port $1 is already in use on this machine" >&2
    return 1
  fi
}
