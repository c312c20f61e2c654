#!/usr/bin/env bash
# The aarch64 install, checked under emulation (tests/aarch64 runs it; root on Linux):
# an arm64 Debian bookworm root (Python 3.11, as on Raspberry Pi OS bookworm) made by
# mmdebstrap from Debian's registry, whose programs run under qemu-user through binfmt_misc;
# in it scripts/install-aarch64.sh installs WHEEL (Cyclone DDS C 11 with DDS-Security, the
# binding built against it, rcan-rtps); then, in a private network namespace (scripts/netns),
# `rcan-rtps run --sim` must reach its ready line, answer /api/status and execute a move
# (release.sh's tour).
#
#   scripts/aarch64-emulated.sh host           arm64 programs run here, or exit 3 saying why
#                                              (installs the host tools below with apt when
#                                              missing, mounts binfmt_misc)
#   scripts/aarch64-emulated.sh prepare WHEEL  the cached root, built when missing (network)
#   scripts/aarch64-emulated.sh smoke WHEEL    the check, offline, from the cached root (exit 4
#                                              when it was not prepared)
#
# prepare, cold (docs/aarch64.md has the times): mmdebstrap, then Cyclone C cross-built on this
# machine by install-aarch64.sh --sysroot, then install-aarch64.sh in the root with WHEEL; the
# root is kept as an archive OUTSIDE the clone, $RCAN_RTPS_AARCH64_CACHE (default
# /var/cache/rcan-rtps)/aarch64-root-KEY.tar.zst, KEY hashing install-aarch64.sh, the vendored
# Cyclone source and the functions below that make the root, so CI's fresh clones on this
# machine reuse it; a changed dependency list of rcan-rtps is installed into it, not rebuilt.
# smoke unpacks it, runs install-aarch64.sh again with WHEEL (Cyclone and the binding found in
# place, the wheel reinstalled) and the tour. Every step says its name; a failure names it.
set -uo pipefail

repo=$(cd "$(dirname "$0")/.." && pwd)
cache=${RCAN_RTPS_AARCH64_CACHE:-/var/cache/rcan-rtps}
suite=bookworm
mirror=http://deb.debian.org/debian
# what a robot computer has for install-aarch64.sh once Cyclone C is built (libssl-dev: the
# cross build's OpenSSL), and curl for the tour
packages=python3,python3-venv,python3-dev,gcc,libc6-dev,libssl-dev,curl,ca-certificates
host_packages=(qemu-user-static binfmt-support mmdebstrap arch-test zstd cmake make
  gcc-aarch64-linux-gnu g++-aarch64-linux-gnu)

say() { printf 'aarch64: %s\n' "$*"; }
fail() { printf 'aarch64: step failed: %s\n' "$*" >&2; exit 1; }
elapsed() { echo $(( $(date +%s) - $1 )); }

# -- the host: qemu-user through binfmt_misc ---------------------------------------------------
binfmt_unavailable() { printf 'aarch64: binfmt_misc unavailable: %s\n' "$*" >&2; exit 3; }
host() {
  [ "$(uname -s)" = Linux ] || binfmt_unavailable "not Linux ($(uname -s))"
  [ "$(id -u)" = 0 ] || binfmt_unavailable "not root: mounting binfmt_misc and chroot need root"
  local missing=() p
  for p in "${host_packages[@]}"; do dpkg -s "$p" >/dev/null 2>&1 || missing+=("$p"); done
  if [ ${#missing[@]} -gt 0 ]; then
    command -v apt-get >/dev/null || fail "host tools: no apt-get to install ${missing[*]}"
    say "installing ${missing[*]}"
    { apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq \
        --no-install-recommends "${missing[@]}"; } >/dev/null 2>&1 \
      || fail "host tools: apt-get install ${missing[*]} did not succeed"
  fi
  if [ ! -f /proc/sys/fs/binfmt_misc/status ]; then
    grep -qw binfmt_misc /proc/filesystems || modprobe binfmt_misc 2>/dev/null || true
    grep -qw binfmt_misc /proc/filesystems \
      || binfmt_unavailable "this kernel has no binfmt_misc file system (/proc/filesystems)"
    local why
    why=$(mount -t binfmt_misc binfmt_misc /proc/sys/fs/binfmt_misc 2>&1) \
      || binfmt_unavailable "mount -t binfmt_misc binfmt_misc /proc/sys/fs/binfmt_misc: $why"
  fi
  # binfmt_misc is there: from here on a problem is a failure, not a reason to skip
  local entry=/proc/sys/fs/binfmt_misc/qemu-aarch64
  [ -f "$entry" ] || update-binfmts --enable qemu-aarch64 >/dev/null 2>&1 \
    || fail "binfmt_misc: update-binfmts --enable qemu-aarch64 (qemu-user-static's entry)"
  [ -f "$entry" ] || fail "binfmt_misc: no qemu-aarch64 entry after update-binfmts --enable"
  grep -q '^enabled' "$entry" || echo 1 >"$entry" \
    || fail "binfmt_misc: the qemu-aarch64 entry is disabled and could not be enabled"
  # F (fix binary): the interpreter is opened at registration, so it works inside a chroot
  grep -q '^flags: .*F' "$entry" \
    || fail "binfmt_misc: qemu-aarch64 is registered without the F flag: a chroot cannot reach its interpreter"
  say "binfmt_misc: qemu-aarch64 enabled ($(/usr/bin/qemu-aarch64-static --version | head -1))"
}

# -- the root --------------------------------------------------------------------------------
cache_key() {  # the recipe: what makes the root, not how it is tested
  { sha256sum "$repo/scripts/install-aarch64.sh" \
      "$repo/scripts/cyclonedds-secure/cyclonedds-11.0.1-src.tar.gz" | cut -d' ' -f1
    declare -f build_root install_wheel copy_sources in_root
    echo "$suite $mirror $packages"; } | sha256sum | cut -c1-16
}

in_root() {  # root, command...: runs in the root (its own /proc and /dev), a clean environment
  local root=$1; shift
  unshare -m --propagation private sh -c '
    r=$1; shift
    mount -t proc proc "$r/proc" && mount --rbind /dev "$r/dev" || exit 1
    exec chroot "$r" /usr/bin/env -i HOME=/root LANG=C.UTF-8 TERM=dumb \
      PATH=/usr/local/sbin:/usr/local/bin:/usr/sbin:/usr/bin:/sbin:/bin "$@"' sh "$root" "$@"
}

copy_sources() {  # root: the install script and the vendored source, as a user's clone has them
  local dest=$1/opt/rcan-rtps-src/scripts
  rm -rf "$1/opt/rcan-rtps-src" && mkdir -p "$dest/cyclonedds-secure" \
    && cp "$repo/scripts/install-aarch64.sh" "$dest/" \
    && cp "$repo/scripts/cyclonedds-secure/cyclonedds-11.0.1-src.tar.gz" "$dest/cyclonedds-secure/" \
    && cp /etc/resolv.conf "$1/etc/resolv.conf" \
    && cp /etc/ssl/certs/ca-certificates.crt "$1/etc/ssl/host-ca-certificates.crt"
}

install_wheel() {  # root, wheel: install-aarch64.sh in the root, emulated
  local root=$1 wheel=$2 start
  start=$(date +%s)
  rm -rf "$root/tmp/wheel" && mkdir -p "$root/tmp/wheel" && cp "$wheel" "$root/tmp/wheel/" \
    || fail "copy the wheel into the root"
  copy_sources "$root" || fail "copy install-aarch64.sh into the root"
  # PIP_CERT: the host's CA bundle, as this machine's TLS to the package index may be re-signed
  in_root "$root" env PIP_CERT=/etc/ssl/host-ca-certificates.crt PIP_DISABLE_PIP_VERSION_CHECK=1 \
    bash /opt/rcan-rtps-src/scripts/install-aarch64.sh \
      --package "/tmp/wheel/$(basename "$wheel")" --venv /opt/rcan-rtps-venv \
    || fail "install-aarch64.sh in the arm64 root (its own message above names the step)"
  say "install-aarch64.sh done in $(elapsed "$start") s (emulated)"
}

build_root() {  # root, wheel: mmdebstrap, then the install
  local root=$1 start
  start=$(date +%s)
  say "building the arm64 $suite root (mmdebstrap; cold, takes minutes)"
  mmdebstrap --quiet --arch=arm64 --variant=apt --include="$packages" "$suite" "$root" "$mirror" \
    >"$cache/aarch64-mmdebstrap.log" 2>&1 || { tail -n 30 "$cache/aarch64-mmdebstrap.log" >&2
      fail "mmdebstrap of an arm64 $suite root (log: $cache/aarch64-mmdebstrap.log)"; }
  say "mmdebstrap done in $(elapsed "$start") s"
  [ "$(in_root "$root" uname -m)" = aarch64 ] || fail "the root's programs do not run as aarch64"
  # a robot's /etc/hosts (mmdebstrap writes none; Cyclone aborts on an unresolvable localhost)
  printf '127.0.0.1\tlocalhost\n::1\tlocalhost ip6-localhost ip6-loopback\n' >"$root/etc/hosts" \
    || fail "write the root's /etc/hosts"
  # Cyclone C cross-built here by the install script's step 2 (minutes, where the same build
  # emulated takes over half an hour on 2 cores); in the root the script then finds it built
  local cross; cross=$(date +%s)
  bash "$repo/scripts/install-aarch64.sh" --sysroot "$root" \
    || fail "install-aarch64.sh --sysroot: Cyclone DDS C cross-built for the root"
  say "Cyclone DDS C cross-built in $(elapsed "$cross") s"
  install_wheel "$root" "$2"
}

work_root=
# the unpacked root is removed whatever happens (its mounts were in a private namespace)
trap '[ -n "$work_root" ] && rm -rf "$work_root"' EXIT
new_work_root() { mktemp -d /var/tmp/rcan-rtps-aarch64.XXXXXX; }

deps_hash() {  # rcan-rtps's dependency list: a change re-installs them into the cached root
  sed -n '/^dependencies = \[/,/^\]/p' "$repo/pyproject.toml" | sha256sum | cut -c1-16
}

absolute() { echo "$(cd "$(dirname "$1")" && pwd)/$(basename "$1")"; }

prepare() {  # wheel: the cached root for this recipe, with this dependency list (needs network)
  local wheel root archive start
  wheel=$(absolute "$1"); [ -f "$wheel" ] || fail "no wheel at $1"
  host || exit $?
  archive=$cache/aarch64-root-$(cache_key).tar.zst
  if [ -f "$archive" ] && [ "$(cat "$archive.deps" 2>/dev/null)" = "$(deps_hash)" ]; then
    say "cached root up to date: $archive"
    return 0
  fi
  mkdir -p "$cache" || fail "create the cache directory $cache"
  root=$(new_work_root) || fail "make a work directory"
  work_root=$root
  start=$(date +%s)
  if [ -f "$archive" ]; then  # same recipe, other dependencies: install them on the cached root
    tar -C "$root" --zstd -xf "$archive" || fail "unpack the cached root $archive"
    install_wheel "$root" "$wheel"
  else
    rmdir "$root" && build_root "$root" "$wheel"
  fi
  local packed; packed=$(date +%s)
  rm -rf "$root/tmp/wheel" "$root/opt/rcan-rtps-src"
  tar -C "$root" --zstd -cf "$archive.partial" . && mv "$archive.partial" "$archive" \
    && deps_hash >"$archive.deps" || fail "pack the root into $archive"
  find "$cache" -maxdepth 1 -name 'aarch64-root-*' ! -name "$(basename "$archive")*" -delete
  say "root cached as $archive ($(du -h "$archive" | cut -f1)) in $(elapsed "$packed") s; prepared in $(elapsed "$start") s"
}

smoke() {  # wheel: the cached root unpacked, WHEEL installed by install-aarch64.sh, the tour
  local wheel root archive start
  wheel=$(absolute "$1"); [ -f "$wheel" ] || fail "no wheel at $1"
  host || exit $?
  archive=$cache/aarch64-root-$(cache_key).tar.zst
  [ -f "$archive" ] && [ "$(cat "$archive.deps" 2>/dev/null)" = "$(deps_hash)" ] || {
    printf 'aarch64: not prepared: no %s for this recipe and dependency list (run: %s prepare WHEEL, with network)\n' \
      "$archive" "$0" >&2; exit 4; }
  root=$(new_work_root) || fail "make a work directory"
  work_root=$root
  start=$(date +%s)
  tar -C "$root" --zstd -xf "$archive" || fail "unpack the cached root $archive"
  say "root unpacked from $archive in $(elapsed "$start") s"
  # what runs in it is arm64 code under qemu: the kernel says x86_64, the root aarch64
  local machine python_elf
  machine=$(in_root "$root" uname -m)
  python_elf=$(od -An -tu2 -j18 -N2 "$root/usr/bin/python3.11" | tr -d ' ')
  [ "$machine" = aarch64 ] && [ "$python_elf" = 183 ] \
    || fail "the root is not aarch64 (uname -m: $machine, python3's ELF machine: $python_elf)"
  say "the root runs as $machine (python3 is an aarch64 ELF) on a $(uname -m) kernel"
  install_wheel "$root" "$wheel"
  say "the tour: run --sim, /api/status, a move (loopback only, private network namespace)"
  local tour_start; tour_start=$(date +%s)
  ln -sfn /opt/rcan-rtps-venv "$root/tmp/venv" && mkdir -p "$root/tmp/state" || fail "prepare the tour"
  # release.sh's own tour, run by the root's bash: work dir /tmp, its venv at /tmp/venv
  "$repo/scripts/netns" bash -c "$(declare -f in_root); in_root \"\$@\"" in_root "$root" \
    bash -c "$(sed -n '/^tour() {/,/^}/p' "$repo/scripts/release.sh"); tour /tmp" \
    || fail "the tour in the arm64 root (run --sim ready, /api/status, a move)"
  say "tour done in $(elapsed "$tour_start") s; smoke done in $(elapsed "$start") s"
}

case "${1:-}" in
  host) host ;;
  key) cache_key ;;  # the cache key of this recipe
  prepare|smoke) [ $# -eq 2 ] || { echo "usage: $0 $1 WHEEL" >&2; exit 2; }; "$1" "$2" ;;
  *) sed -n '2,/^set -uo/p' "$0" | sed '$d' >&2; exit 2 ;;
esac
