#!/usr/bin/env bash
# Installs what vkterrain needs on a fresh Debian 12 machine: the Vulkan loader,
# lavapipe (CPU Vulkan driver), validation layers, Xvfb and xdotool for window tests, and the
# toolchain shaderc's build-from-source needs (cmake, ninja, python3, g++), and GDAL (the
# terrain file reader: libgdal-dev, about 60 MB with its libraries).
# Idempotent: does nothing when everything is present.
set -euo pipefail

need=()
have_pkg() { dpkg-query -W -f='${Status}' "$1" 2>/dev/null | grep -q "install ok installed"; }
for p in libvulkan1 mesa-vulkan-drivers vulkan-validationlayers vulkan-tools \
         xvfb xauth xdotool cmake ninja-build python3 g++ pkg-config curl ca-certificates fonts-dejavu-core procps libx11-dev libxkbcommon-x11-0 \
         libwayland-client0 libxcursor1 libxrandr2 libxi6 libgdal-dev; do
  have_pkg "$p" || need+=("$p")
done

if ((${#need[@]})); then
  sudo=""
  [ "$(id -u)" = 0 ] || sudo="sudo"
  echo "install-deps: installing ${need[*]}" >&2
  export DEBIAN_FRONTEND=noninteractive
  $sudo apt-get update -q >&2
  $sudo apt-get install -y -q --no-install-recommends "${need[@]}" >&2
fi

if ! command -v cargo >/dev/null 2>&1 && [ ! -x "$HOME/.cargo/bin/cargo" ]; then
  echo "install-deps: installing the Rust toolchain (rustup, stable)" >&2
  curl --proto '=https' --tlsv1.2 -sSf https://sh.rustup.rs | sh -s -- -y --profile minimal -c rustfmt,clippy >&2
fi
export PATH="$HOME/.cargo/bin:$PATH"
if command -v rustup >/dev/null 2>&1; then
  installed=$(rustup component list --installed 2>/dev/null || true)
  for c in rustfmt clippy; do
    echo "$installed" | grep -q "^$c" || rustup component add "$c" >&2
  done
fi
