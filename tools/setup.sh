#!/usr/bin/env bash
# Installs, through apt-get on Debian 12, what this project needs and the machine lacks:
#   - a Vulkan driver when the loader finds none: Mesa lavapipe from bookworm-backports (about
#     3x faster than bookworm's; it runs everything on the CPU) and the loader, libvulkan1;
#   - with --tests, what the test command needs besides: the Khronos validation layer
#     (vulkan-validationlayers), Debian's chromium (headless, for the viewer's browser test;
#     its chromium-common brings SwiftShader and the newer build of the layer whose
#     GPU-assisted checks one test uses), Open MPI's mpirun for the two-process training
#     tests, ffmpeg for the video import's tests, and Python's venv and pip for the Python
#     package's tests.
# Does nothing where everything is there. Usage: tools/setup.sh [--tests]
set -euo pipefail

SUDO=""
[ "$(id -u)" -eq 0 ] || SUDO="sudo"
apt_updated=0
apt_update() {
  [ $apt_updated = 1 ] || $SUDO apt-get update -qq
  apt_updated=1
}
installed() {
  local status
  status=$(dpkg-query -W -f='${db:Status-Status}\n' "$@" 2>/dev/null) || return 1
  ! grep -qvx installed <<<"$status"
}
have_vulkan_device() {
  # The loader must exist, and a driver manifest: installed, or named by the environment.
  # (grep reads all of ldconfig's output: with -q it could stop early, and pipefail would
  # count ldconfig's broken pipe as a failure.)
  ldconfig -p | grep 'libvulkan\.so\.1' >/dev/null || return 1
  [ -n "${VK_DRIVER_FILES:-}${VK_ICD_FILENAMES:-}" ] && return 0
  local f
  for f in /usr/share/vulkan/icd.d/*.json /etc/vulkan/icd.d/*.json; do
    [ -e "$f" ] && return 0
  done
  return 1
}

if ! have_vulkan_device; then
  echo "setup: no Vulkan device found; installing Mesa lavapipe from bookworm-backports" >&2
  if ! grep -rqs 'bookworm-backports' /etc/apt/sources.list /etc/apt/sources.list.d/; then
    echo 'deb http://deb.debian.org/debian bookworm-backports main' |
      $SUDO tee /etc/apt/sources.list.d/bookworm-backports.list >/dev/null
  fi
  apt_update
  $SUDO env DEBIAN_FRONTEND=noninteractive apt-get install -y -qq -t bookworm-backports \
    mesa-vulkan-drivers libvulkan1 >/dev/null
fi

if [ "${1:-}" = --tests ]; then
  needed=()
  for p in vulkan-validationlayers chromium chromium-common openmpi-bin ffmpeg; do
    installed "$p" || needed+=("$p")
  done
  # The Python package's tests run in a fresh venv (tools/python-check.sh): Python 3.9 or
  # later with venv and pip, which a Debian machine may lack.
  if ! python3 -c 'import sys, venv, ensurepip; assert sys.version_info >= (3, 9)' 2>/dev/null; then
    needed+=(python3 python3-venv python3-pip)
  fi
  if [ ${#needed[@]} -gt 0 ]; then
    echo "setup: installing ${needed[*]}" >&2
    apt_update
    $SUDO env DEBIAN_FRONTEND=noninteractive apt-get install -y -qq --no-install-recommends \
      "${needed[@]}" >/dev/null
  fi
fi
