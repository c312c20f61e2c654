#!/usr/bin/env bash
# Builds Eclipse Cyclone DDS C 11.0.1 WITH DDS-Security, and the cyclonedds Python binding
# against it, into PREFIX (PyPI's cyclonedds wheel is built without security, so SROS2 needs
# this; the product's default install keeps the wheel):
#   PREFIX/c      the C install: lib/libddsc.so.11, lib/libdds_security_{auth,ac,crypto}.so
#   PREFIX/venv   a venv with the binding built from its sdist against PREFIX/c, and
#                 rcan-rtps's runtime dependencies (run rcan-rtps from source with PYTHONPATH)
#
#   bash scripts/cyclonedds-secure/build.sh PREFIX     # PYTHON=python3.11 to choose the interpreter
#
# Idempotent: a finished PREFIX carries a stamp of what it was built from and is left alone.
# Run with CYCLONEDDS_HOME=PREFIX/c (the binding's loader needs it).
# Needs cmake, a C compiler, OpenSSL headers and patchelf (Debian: cmake g++ libssl-dev
# patchelf; installed when missing and run as root). The C source is vendored next to this
# script (SOURCE.md).
set -euo pipefail

here=$(cd "$(dirname "$0")" && pwd)
repo=$(cd "$here/../.." && pwd)
prefix=${1:?usage: build.sh PREFIX}
mkdir -p "$prefix"
prefix=$(cd "$prefix" && pwd -P)  # physical: the venv and rpaths must outlive links
python=${PYTHON:-python3}
tarball=$here/cyclonedds-11.0.1-src.tar.gz
version=11.0.1

stamp=$({ sha256sum "$tarball" "$here/build.sh" | cut -d' ' -f1; "$python" -V; } | sha256sum | cut -c1-16)
if [ -f "$prefix/.stamp" ] && [ "$(cat "$prefix/.stamp")" = "$stamp" ]; then
  echo "secure Cyclone up to date in $prefix"
  exit 0
fi

need=()
command -v cmake >/dev/null || need+=(cmake)
command -v cc >/dev/null || need+=(gcc)
command -v patchelf >/dev/null || need+=(patchelf)
[ -f /usr/include/openssl/ssl.h ] || need+=(libssl-dev)
if [ ${#need[@]} -gt 0 ]; then
  if [ "$(id -u)" = 0 ] && command -v apt-get >/dev/null; then
    apt-get install -y --no-install-recommends "${need[@]}"
  else
    echo "missing build tools: ${need[*]} (Debian/Ubuntu: apt-get install ${need[*]})" >&2
    exit 1
  fi
fi

rm -rf "$prefix/c" "$prefix/venv" "$prefix/src" "$prefix/build" "$prefix/.stamp"
mkdir -p "$prefix/src"
tar -xzf "$tarball" -C "$prefix/src"
jobs=$(nproc 2>/dev/null || echo 2)

echo "== Cyclone DDS C $version (security on) =="
cmake -S "$prefix/src/cyclonedds-$version" -B "$prefix/build" \
  -DCMAKE_BUILD_TYPE=Release -DCMAKE_INSTALL_PREFIX="$prefix/c" \
  -DCMAKE_INSTALL_RPATH='$ORIGIN' -DCMAKE_INSTALL_LIBDIR=lib \
  -DENABLE_SECURITY=ON -DENABLE_SSL=ON -DENABLE_SHM=OFF -DENABLE_ICEORYX=OFF \
  -DBUILD_TESTING=OFF -DBUILD_EXAMPLES=OFF -DBUILD_DDSPERF=OFF -DBUILD_IDLC=ON
cmake --build "$prefix/build" --parallel "$jobs"
cmake --install "$prefix/build"
for plugin in auth ac crypto; do
  [ -f "$prefix/c/lib/libdds_security_$plugin.so" ] || {
    echo "the build did not produce libdds_security_$plugin.so" >&2; exit 1; }
done

echo "== the cyclonedds $version binding, built against it =="
"$python" -m venv "$prefix/venv"
"$prefix/venv/bin/pip" install -q --upgrade pip
CYCLONEDDS_HOME="$prefix/c" "$prefix/venv/bin/pip" install -q \
  --no-binary cyclonedds "cyclonedds==$version"
# The binding's extensions link libddsc.so.11 by name: point them at this install (no
# ldconfig, no LD_LIBRARY_PATH). Its ctypes loader still needs CYCLONEDDS_HOME=PREFIX/c at
# run time: without it, it takes the first libddsc on the library path (Debian's 0.10, say).
for ext in "$prefix"/venv/lib/python3*/site-packages/cyclonedds/*.so; do
  patchelf --set-rpath "$prefix/c/lib" "$ext"
done
# rcan-rtps's runtime dependencies (not rcan-rtps itself: it runs from the tree's src/),
# with the binding above kept.
deps=$("$python" - "$repo/pyproject.toml" <<'EOF'
import re, sys
text = open(sys.argv[1], encoding="utf-8").read()
try:
    import tomllib
    deps = tomllib.loads(text)["project"]["dependencies"]
except ImportError:  # Python 3.10: the list's quoted strings, comments left out
    block = re.search(r"^dependencies = \[(.*?)^\]", text, re.S | re.M).group(1)
    deps = re.findall(r'^\s*"([^"]+)"', block, re.M)
print("\n".join(d for d in deps if not d.startswith("cyclonedds")))
EOF
)
mapfile -t deps <<<"$deps"
"$prefix/venv/bin/pip" install -q "${deps[@]}" pytest pytest-asyncio

rm -rf "$prefix/build" "$prefix/src"
echo "$stamp" >"$prefix/.stamp"
echo "secure Cyclone ready: CYCLONEDDS_HOME=$prefix/c $prefix/venv/bin/python"
