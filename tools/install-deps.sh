#!/usr/bin/env bash
# Installs what vkterrain needs on a fresh Debian 12 machine: the Vulkan loader,
# lavapipe (CPU Vulkan driver), validation layers, Xvfb and xdotool for window tests,
# Debian's shader compiler (libshaderc-dev, glslang-dev, spirv-tools: merged below into the
# one static archive the shaderc crate links), the toolchain a build of shaderc from source
# would need (cmake, ninja, python3, g++), and GDAL (the terrain file reader: libgdal-dev,
# about 60 MB with its libraries).
# Idempotent: does nothing when everything is present.
set -euo pipefail

need=()
have_pkg() { dpkg-query -W -f='${Status}' "$1" 2>/dev/null | grep -q "install ok installed"; }
for p in libvulkan1 mesa-vulkan-drivers vulkan-validationlayers vulkan-tools \
         xvfb xauth xdotool cmake ninja-build python3 g++ pkg-config curl ca-certificates fonts-dejavu-core procps libx11-dev libxkbcommon-x11-0 \
         libwayland-client0 libxcursor1 libxrandr2 libxi6 libgdal-dev \
         libshaderc-dev glslang-dev spirv-tools; do
  have_pkg "$p" || need+=("$p")
done

if ((${#need[@]})); then
  sudo=""
  [ "$(id -u)" = 0 ] || sudo="sudo"
  echo "install-deps: installing ${need[*]}" >&2
  export DEBIAN_FRONTEND=noninteractive
  $sudo apt-get update -q >&2
  # A package this Debian does not have (shaderc's, on an older release) is left out,
  # and the build then compiles shaderc from source (tools/cargo.sh says so).
  $sudo apt-get install -y -q --no-install-recommends "${need[@]}" >&2 ||
    $sudo apt-get install -y -q --no-install-recommends \
      $(for p in "${need[@]}"; do apt-cache show "$p" >/dev/null 2>&1 && echo "$p"; done) >&2
fi

# Debian splits shaderc: libshaderc_combined.a holds shaderc alone, and glslang and
# SPIRV-Tools ship as separate static archives. The shaderc crate links one archive named
# libshaderc_combined.a, so merge them (ar -M) into the user's cache, outside the clone;
# tools/env.sh points SHADERC_LIB_DIR at it. Without it the crate builds shaderc's C++ from
# source (about 10 minutes on 2 cores).
lib=/usr/lib/$(uname -m)-linux-gnu
shaderc_dir="${XDG_CACHE_HOME:-$HOME/.cache}/vkterrain/shaderc"
parts=(shaderc_combined glslang MachineIndependent OSDependent GenericCodeGen OGLCompiler SPIRV
       SPIRV-Tools-opt SPIRV-Tools glslang-default-resource-limits)
missing=()
for p in "${parts[@]}"; do [ -f "$lib/lib$p.a" ] || missing+=("lib$p.a"); done
if ((${#missing[@]})); then
  echo "install-deps: Debian's shaderc libraries are missing (${missing[*]}): shaderc will be built from source" >&2
elif [ ! -f "$shaderc_dir/libshaderc_combined.a" ] || [ "$lib/libshaderc_combined.a" -nt "$shaderc_dir/libshaderc_combined.a" ]; then
  mkdir -p "$shaderc_dir"
  tmp=$(mktemp "$shaderc_dir/merge.XXXXXX")
  { echo "CREATE $tmp.a"; for p in "${parts[@]}"; do echo "ADDLIB $lib/lib$p.a"; done; echo SAVE; echo END; } | ar -M
  ranlib "$tmp.a"
  mv "$tmp.a" "$shaderc_dir/libshaderc_combined.a"
  rm -f "$tmp"
  echo "install-deps: merged Debian's shaderc, glslang and SPIRV-Tools into $shaderc_dir/libshaderc_combined.a" >&2
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
