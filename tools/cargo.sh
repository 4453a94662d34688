#!/usr/bin/env bash
# Runs cargo with the given arguments. On a machine's first build it says first what that
# build does and how far it has got every 30 s (minutes can pass with no cargo output).
# With Debian's shaderc merged by tools/install-deps.sh (SHADERC_LIB_DIR) the first build
# is the crates alone; without it, shaderc's C++ (glslang, SPIRV-Tools) is built from
# source as well, once per machine.
set -euo pipefail
target="${CARGO_TARGET_DIR:?source tools/env.sh first}"
built() { ls "$target"/debug/deps/libshaderc_sys-*.rlib >/dev/null 2>&1; }
if built; then
  exec cargo "$@"
fi
if [ -n "${SHADERC_LIB_DIR:-}" ]; then
  cat >&2 <<EOT
vkterrain: first build on this machine: about 300 crates, linked with Debian's shaderc
  ($SHADERC_LIB_DIR). Measured on 2 cores: about 11 minutes. Later builds reuse it
  (target dir: $target).
EOT
else
  cat >&2 <<EOT
vkterrain: first build on this machine: about 300 crates and shaderc's C++ (glslang and
  SPIRV-Tools) built from source, because Debian's shaderc libraries were not found
  (tools/install-deps.sh installs them on Debian 12). Measured on 2 cores: about 24
  minutes, most of it the C++. Later builds reuse it (target dir: $target).
EOT
fi
start=$(date +%s)
(
  while sleep 30; do
    built && break
    ninja_file=$(ls "$target"/debug/build/shaderc-sys-*/out/build/build.ninja 2>/dev/null | head -n1 || true)
    elapsed=$(( $(date +%s) - start ))
    crates=$(ls "$target"/debug/deps/*.rlib 2>/dev/null | wc -l)
    if [ -n "$ninja_file" ]; then
      dir=$(dirname "$ninja_file")
      total=$(grep -c '^build [^:]*\.o:' "$ninja_file" || true)
      done_=$(find "$dir" -name '*.o' | wc -l)
      echo "vkterrain: first build, $((elapsed / 60)) min $((elapsed % 60)) s: shaderc C++ $done_ of $total objects" >&2
    else
      echo "vkterrain: first build, $((elapsed / 60)) min $((elapsed % 60)) s: $crates crates compiled" >&2
    fi
  done
) &
watcher=$!
trap 'kill "$watcher" 2>/dev/null || true' EXIT
cargo "$@"
