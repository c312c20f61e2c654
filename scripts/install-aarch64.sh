#!/usr/bin/env bash
# Installs rcan-rtps on a Linux aarch64 robot computer (a Jetson on Ubuntu 22.04 / JetPack 6
# with Python 3.10, a Raspberry Pi on Raspberry Pi OS bookworm with Python 3.11), where PyPI
# has no `cyclonedds` wheel:
#   1. checks what the build needs, and names every missing piece with its package
#   2. builds Cyclone DDS C 11.0.1 WITH DDS-Security from the source vendored beside this
#      script (scripts/cyclonedds-secure) and installs it under PREFIX
#   3. makes it findable: rpaths, so nothing needs ldconfig or LD_LIBRARY_PATH; as root also
#      an ld.so.conf.d entry and ldconfig, for other programs linking libddsc
#   4. builds the cyclonedds 11.0.1 Python binding from its PyPI sdist against PREFIX, in VENV
#   5. installs rcan-rtps into VENV and checks that it loads this Cyclone
#
#   bash scripts/install-aarch64.sh [--prefix DIR] [--venv DIR] [--package SPEC] [--no-ldconfig]
#   bash scripts/install-aarch64.sh --sysroot ROOT [--prefix DIR]
#
#   --prefix DIR   where Cyclone DDS C goes (default /opt/cyclonedds-11.0.1 as root, else
#                  ~/.local/cyclonedds-11.0.1)
#   --venv DIR     the virtual environment for rcan-rtps (default ~/rcan-rtps-venv)
#   --package SPEC what pip installs as rcan-rtps: a wheel, a source tree, or a requirement
#                  such as 'rcan-rtps[mcp]' (default: the source tree holding this script)
#   --no-ldconfig  as root, leave the dynamic linker's configuration alone
#   --sysroot ROOT step 2 only, cross-built on an x86_64 machine with Debian's aarch64 cross
#                  compilers for the arm64 root file system ROOT (with libc6-dev and
#                  libssl-dev in it), installed into ROOT/PREFIX; this script run later in
#                  that root (or on the robot it is) finds it built and does steps 3 to 5.
#                  For boards that build slowly, and for CI's emulated root.
# PYTHON chooses the interpreter (default python3). Re-running is cheap: a PREFIX built from
# the same source and options is kept, and the binding is rebuilt only when missing.
# It runs on any Linux (x86_64 too); only aarch64 lacks the wheel that makes it unneeded.
set -uo pipefail

here=$(cd "$(dirname "$0")" && pwd)
tarball=$here/cyclonedds-secure/cyclonedds-11.0.1-src.tar.gz
version=11.0.1
python=${PYTHON:-python3}
prefix=
venv=$HOME/rcan-rtps-venv
package=
ldconfig=yes
sysroot=

say() { printf '%s\n' "$*"; }
die() { printf 'install-aarch64: %s\n' "$*" >&2; exit 1; }
usage() { sed -n '/^#   bash/,/^# It runs/p' "$0" | sed 's/^# \{0,1\}//' >&2; exit 2; }

while [ $# -gt 0 ]; do
  case $1 in
    --prefix) [ $# -ge 2 ] || usage; prefix=$2; shift 2 ;;
    --venv) [ $# -ge 2 ] || usage; venv=$2; shift 2 ;;
    --package) [ $# -ge 2 ] || usage; package=$2; shift 2 ;;
    --no-ldconfig) ldconfig=no; shift ;;
    --sysroot) [ $# -ge 2 ] || usage; sysroot=$(cd "$2" 2>/dev/null && pwd -P) || die "no directory $2"; shift 2 ;;
    -h|--help) usage ;;
    *) say "unknown argument: $1" >&2; usage ;;
  esac
done
# as root, or for another root file system: /opt; else the user's own
if [ -z "$prefix" ]; then
  if [ "$(id -u)" = 0 ] || [ -n "$sysroot" ]; then prefix=/opt/cyclonedds-$version
  else prefix=$HOME/.local/cyclonedds-$version; fi
fi
case $prefix in /*) ;; *) prefix=$PWD/$prefix ;; esac
if [ -z "$package" ] && [ -z "$sysroot" ]; then
  [ -f "$here/../pyproject.toml" ] && grep -q '^name = "rcan-rtps"' "$here/../pyproject.toml" \
    || die "no source tree around this script: say what to install with --package (a wheel, or rcan-rtps)"
  package=$(cd "$here/.." && pwd)
fi

step=
run_step() {  # name, command...: runs one step; on failure names it and stops
  step=$1; shift
  say "== $step"
  "$@" || die "step failed: $step${log:+ (its output: $log)}"
}

# -- 1. prerequisites: all of them checked, every missing one named ---------------------------
missing=() why=()
need() { missing+=("$1"); why+=("$2"); }
report_missing() {
  [ ${#missing[@]} -eq 0 ] && return 0
  local i pkgs sudo=
  say "missing prerequisites:" >&2
  for i in "${!missing[@]}"; do say "  - ${missing[$i]}: ${why[$i]}" >&2; done
  pkgs=$(printf '%s\n' "${missing[@]}" | sed 's/^gcc$/build-essential/; s/^g++$/build-essential/; s/^make$/build-essential/' | sort -u | tr '\n' ' ')
  [ "$(id -u)" = 0 ] || sudo="sudo "
  say "on Ubuntu, Debian or Raspberry Pi OS: ${sudo}apt-get install ${pkgs% }" >&2
  [ -n "$sysroot" ] && say "(libssl-dev and libc6-dev go into the arm64 root $sysroot, the rest on this machine)" >&2
  exit 1
}
check_cmake() {
  if ! command -v cmake >/dev/null; then
    need cmake "no cmake (3.16 or newer)"
  else
    local cv; cv=$(cmake --version | sed -n 's/^cmake version \([0-9]*\.[0-9]*\).*/\1/p')
    printf '%s\n3.16\n' "$cv" | sort -V -C 2>/dev/null && [ "$cv" != 3.16 ] \
      && need cmake "cmake $cv is older than the 3.16 Cyclone DDS needs"
  fi
  command -v make >/dev/null || need make "no make (cmake's build tool)"
}
check_python() {
  if ! command -v "$python" >/dev/null; then
    need python3 "no $python on PATH"
    return
  fi
  "$python" -c 'import sys; sys.exit(sys.version_info < (3, 10))' \
    || die "rcan-rtps needs Python 3.10 or newer; $python is $("$python" -V 2>&1) (choose another with PYTHON=python3.11)"
  local pv; pv=$("$python" -c 'import sys; print("%d.%d" % sys.version_info[:2])')
  "$python" -c 'import venv, ensurepip' 2>/dev/null \
    || need "python3-venv" "$python cannot create virtual environments (no ensurepip; also called python$pv-venv)"
  "$python" -c 'import os, sys, sysconfig
sys.exit(not os.path.exists(os.path.join(sysconfig.get_paths()["include"], "Python.h")))' \
    || need "python3-dev" "no Python.h for $python, which the binding's C extensions compile against (also called python$pv-dev)"
  command -v cc >/dev/null || need gcc "no C compiler (cc) for the binding's C extensions"
}
check_native_build() {  # what building Cyclone DDS C here needs
  check_cmake
  if command -v cc >/dev/null && ! echo '#include <openssl/ssl.h>' | cc -E -x c - >/dev/null 2>&1; then
    need libssl-dev "no OpenSSL headers (openssl/ssl.h): DDS-Security, which SROS2 needs, is built on OpenSSL"
  fi
  command -v c++ >/dev/null || need g++ "no C++ compiler (c++): Cyclone DDS's cmake project asks for one"
}
check_cross_build() {  # what building it here for the arm64 root $sysroot needs
  check_cmake
  command -v aarch64-linux-gnu-gcc >/dev/null || need gcc-aarch64-linux-gnu "no aarch64 cross compiler (aarch64-linux-gnu-gcc)"
  command -v aarch64-linux-gnu-g++ >/dev/null || need g++-aarch64-linux-gnu "no aarch64 C++ cross compiler (aarch64-linux-gnu-g++)"
  [ -f "$sysroot/usr/include/openssl/ssl.h" ] || need libssl-dev "no OpenSSL headers in $sysroot (libssl-dev of the root)"
  [ -e "$sysroot/usr/lib/aarch64-linux-gnu/libc.so" ] || need libc6-dev "no C library to link against in $sysroot (libc6-dev of the root)"
}
check_prerequisites() {
  [ "$(uname -s)" = Linux ] || die "this script is for Linux (found $(uname -s))"
  [ -f "$tarball" ] || die "the vendored Cyclone DDS source is missing: $tarball"
  if [ -n "$sysroot" ]; then
    [ -x "$sysroot/bin/sh" ] || die "--sysroot $sysroot is not a root file system (no bin/sh)"
    check_cross_build
    report_missing
    say "cross-building for $sysroot with $(aarch64-linux-gnu-gcc --version | head -1)"
    return
  fi
  local arch; arch=$(uname -m)
  [ "$arch" = aarch64 ] || say "note: this is $arch, not aarch64; PyPI's cyclonedds wheel may serve here without a build"
  check_python
  if cyclone_built; then
    say "(Cyclone DDS C $version is built in $prefix: cmake and OpenSSL's headers are not needed)"
  else
    check_native_build
  fi
  report_missing
  say "Python $("$python" -c 'import platform; print(platform.python_version())'), $(cc --version | head -1)"
}

# -- 2. Cyclone DDS C 11.0.1 with DDS-Security --------------------------------------------------
cmake_options=(-DCMAKE_BUILD_TYPE=Release -DCMAKE_INSTALL_LIBDIR=lib
  "-DCMAKE_INSTALL_RPATH=\$ORIGIN;\$ORIGIN/../lib"
  -DENABLE_SECURITY=ON -DENABLE_SSL=ON -DENABLE_SHM=OFF -DENABLE_ICEORYX=OFF
  -DBUILD_TESTING=OFF -DBUILD_EXAMPLES=OFF -DBUILD_DDSPERF=OFF -DBUILD_IDLC=ON)
c_stamp() { { sha256sum "$tarball" | cut -d' ' -f1; printf '%s\n' "${cmake_options[@]}"; } | sha256sum | cut -c1-16; }
elf_machine() { od -An -tu2 -j18 -N2 "$1" 2>/dev/null | tr -d ' '; }  # e_machine: 183 is aarch64
cyclone_built() {  # the install in (sysroot+)prefix came from this source and these options, for this machine
  local dest=$sysroot$prefix want
  if [ -n "$sysroot" ]; then want=183; else want=$(elf_machine /bin/sh); fi
  [ -f "$dest/.rcan-rtps-stamp" ] && [ "$(cat "$dest/.rcan-rtps-stamp")" = "$(c_stamp)" ] \
    && [ "$(elf_machine "$dest/lib/libddsc.so.$version")" = "$want" ]
}
build_cyclone() {
  if cyclone_built; then say "Cyclone DDS C $version already in $sysroot$prefix"; return 0; fi
  local work cross=()
  work=$(mktemp -d) || return 1
  log=$work/build.log
  if [ -n "$sysroot" ]; then  # Debian's cross compilers, the root's headers and libraries
    cat >"$work/aarch64.cmake" <<EOF
set(CMAKE_SYSTEM_NAME Linux)
set(CMAKE_SYSTEM_PROCESSOR aarch64)
set(CMAKE_SYSROOT "$sysroot")
set(CMAKE_C_COMPILER aarch64-linux-gnu-gcc)
set(CMAKE_CXX_COMPILER aarch64-linux-gnu-g++)
set(CMAKE_FIND_ROOT_PATH_MODE_PROGRAM NEVER)
set(CMAKE_FIND_ROOT_PATH_MODE_LIBRARY ONLY)
set(CMAKE_FIND_ROOT_PATH_MODE_INCLUDE ONLY)
set(CMAKE_FIND_ROOT_PATH_MODE_PACKAGE ONLY)
EOF
    cross=(-DCMAKE_TOOLCHAIN_FILE="$work/aarch64.cmake")
    say "cross-building in $work"
  else
    say "building in $work (a few minutes on a Jetson, longer on a Raspberry Pi)"
  fi
  # the install goes to $prefix as the robot sees it; a cross build puts it below the root
  tar -xzf "$tarball" -C "$work" \
    && cmake -S "$work/cyclonedds-$version" -B "$work/build" -DCMAKE_INSTALL_PREFIX="$prefix" \
         "${cross[@]}" "${cmake_options[@]}" >"$log" 2>&1 \
    && cmake --build "$work/build" --parallel "$(nproc 2>/dev/null || echo 2)" >>"$log" 2>&1 \
    && mkdir -p "$sysroot$prefix" \
    && DESTDIR=$sysroot cmake --install "$work/build" >>"$log" 2>&1 \
    || { tail -n 30 "$log" >&2; return 1; }
  local plugin
  for plugin in auth ac crypto; do
    [ -f "$sysroot$prefix/lib/libdds_security_$plugin.so" ] \
      || { say "the build made no libdds_security_$plugin.so: DDS-Security is off" >&2; return 1; }
  done
  c_stamp >"$sysroot$prefix/.rcan-rtps-stamp"
  rm -rf "$work"; log=
}

# -- 3. findable without LD_LIBRARY_PATH ---------------------------------------------------------
register_library() {
  # The binding's extensions get an rpath to $prefix/lib (step 4) and its ctypes loader keeps
  # the path it was built against, so rcan-rtps needs no ldconfig. As root we add the lib
  # directory to the linker's cache too, for anything else built against this Cyclone.
  if [ "$ldconfig" = yes ] && [ "$(id -u)" = 0 ] && command -v ldconfig >/dev/null; then
    echo "$prefix/lib" >/etc/ld.so.conf.d/rcan-rtps-cyclonedds.conf && ldconfig \
      && say "ldconfig: $prefix/lib registered (/etc/ld.so.conf.d/rcan-rtps-cyclonedds.conf)"
  else
    say "no ldconfig change (not root, or --no-ldconfig): rpaths point at $prefix/lib"
  fi
}

# -- 4. the binding, built against it ---------------------------------------------------------------
binding_matches() {  # the venv's binding loads this prefix's libddsc, with no help from the environment
  [ -x "$venv/bin/python" ] && env -u CYCLONEDDS_HOME -u LD_LIBRARY_PATH "$venv/bin/python" - "$prefix" <<'EOF' 2>/dev/null
import os, sys
from cyclonedds import __library__, _clayer  # noqa: F401  (_clayer: its libddsc must resolve)
from importlib.metadata import version
ok = version("cyclonedds") == "11.0.1" and os.path.realpath(os.path.dirname(__library__.library_path)) \
    == os.path.realpath(os.path.join(sys.argv[1], "lib"))
sys.exit(not ok)
EOF
}
pin_library() {
  # The binding's ctypes loader tries CYCLONEDDS_HOME, then any libddsc the system finds (a
  # Debian libddsc0, or ROS 2's Cyclone 0.10 on LD_LIBRARY_PATH once ROS is sourced), and only
  # then the one it was built against; its C extensions, through their rpath, use this one.
  # Two Cyclones in one process is silent trouble, so this venv's interpreters start with
  # CYCLONEDDS_HOME defaulting to PREFIX (a .pth file site.py runs; a set one is kept).
  local site
  site=$("$venv/bin/python" -c 'import sysconfig; print(sysconfig.get_paths()["purelib"])') || return 1
  printf 'import os; os.environ.setdefault("CYCLONEDDS_HOME", %s)\n' \
    "$("$venv/bin/python" -c 'import sys; print(repr(sys.argv[1]))' "$prefix")" \
    >"$site/rcan-rtps-cyclonedds-home.pth"
}
build_binding() {
  if [ ! -x "$venv/bin/python" ]; then
    "$python" -m venv "$venv" || return 1
    "$venv/bin/python" -m pip install -q --upgrade pip || return 1
  fi
  pin_library || return 1
  if binding_matches; then say "the cyclonedds $version binding in $venv already uses $prefix"; return 0; fi
  # --no-cache-dir: a wheel pip built earlier against another Cyclone must not be reused.
  # LDFLAGS: the extensions find libddsc.so.11 through their rpath, not the linker's cache.
  CYCLONEDDS_HOME=$prefix LDFLAGS="-Wl,-rpath,$prefix/lib ${LDFLAGS:-}" \
    "$venv/bin/python" -m pip install -q --no-cache-dir --force-reinstall --no-deps \
    --no-binary cyclonedds "cyclonedds==$version" || return 1
  "$venv/bin/python" -m pip install -q "cyclonedds==$version" || return 1  # its own dependencies
  binding_matches || { say "the binding was built but does not load $prefix/lib/libddsc.so" >&2; return 1; }
}

# -- 5. rcan-rtps -----------------------------------------------------------------------------------
install_rcan_rtps() {
  # with its dependencies, then once more forced: an earlier build carrying the same version
  # number (a source tree, a rebuilt wheel) must not stay in place
  "$venv/bin/python" -m pip install -q "$package" \
    && "$venv/bin/python" -m pip install -q --force-reinstall --no-deps "$package" || return 1
  env -u CYCLONEDDS_HOME "$venv/bin/rcan-rtps" --version || return 1
  # which libddsc the process really maps: exactly one, this prefix's (_clayer's rpath and the
  # ctypes loader could otherwise disagree, e.g. with another Cyclone on the library path)
  env -u CYCLONEDDS_HOME "$venv/bin/python" - "$prefix" <<'EOF'
import os, sys
import cyclonedds.domain, rcan_rtps.ros  # noqa: F401  (rcan_rtps.ros checks the binding)
from cyclonedds.internal import load_cyclonedds
load_cyclonedds()
with open("/proc/self/maps") as maps:
    loaded = sorted({line.split()[-1] for line in maps if "/libddsc.so" in line})
print("rcan-rtps loads", " ".join(loaded))
want = os.path.realpath(os.path.join(sys.argv[1], "lib"))
sys.exit(len(loaded) != 1 or os.path.dirname(os.path.realpath(loaded[0])) != want)
EOF
}

log=
run_step "1/5 prerequisites" check_prerequisites
run_step "2/5 Cyclone DDS C $version with DDS-Security into $sysroot$prefix" build_cyclone
if [ -n "$sysroot" ]; then
  say "done: Cyclone DDS C $version cross-built into $sysroot$prefix; run this script in that root (or on the robot it is) for steps 3 to 5"
  exit 0
fi
run_step "3/5 library lookup" register_library
run_step "4/5 the cyclonedds $version binding into $venv" build_binding
run_step "5/5 rcan-rtps ($package) into $venv" install_rcan_rtps
say "done: $venv/bin/rcan-rtps run --sim   ($venv/bin/rcan-rtps doctor --report shows what it loaded)"
