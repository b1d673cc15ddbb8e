#!/usr/bin/env bash
# Makes a Vulkan driver available for the GPU-path tests (cargo feature `gpu`, burn's wgpu
# backend): where no Vulkan driver is installed, installs Mesa's software one (llvmpipe,
# Debian's `mesa-vulkan-drivers` and `libvulkan1`) with apt-get when it can. Otherwise it
# says so and exits 3, and the GPU tests skip with a message. Idempotent.
set -uo pipefail
have_driver() {
  for f in /usr/share/vulkan/icd.d/*.json /etc/vulkan/icd.d/*.json; do
    [ -e "$f" ] && return 0
  done
  return 1
}
if have_driver; then
  exit 0
fi
if command -v apt-get >/dev/null && [ "$(id -u)" = 0 ]; then
  pkgs="mesa-vulkan-drivers libvulkan1"
  if ! DEBIAN_FRONTEND=noninteractive apt-get install -y -q --no-install-recommends $pkgs >&2; then
    apt-get update -q >&2 && DEBIAN_FRONTEND=noninteractive apt-get install -y -q --no-install-recommends $pkgs >&2
  fi
fi
if ! have_driver; then
  echo "setup_vulkan.sh: no Vulkan driver installed and none could be (needs root and apt-get); the GPU tests will skip" >&2
  exit 3
fi
