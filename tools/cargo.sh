#!/usr/bin/env bash
# Runs cargo with the given arguments. On a machine's first build it says first what that
# build does and, while shaderc's C++ compiles (minutes with no cargo output), how far it
# has got every 30 s: build.rs compiles the shaders with shaderc, whose C++ (glslang,
# SPIRV-Tools) is built from source once per machine.
set -euo pipefail
target="${CARGO_TARGET_DIR:?source tools/env.sh first}"
built() { ls -d "$target"/debug/build/shaderc-sys-*/out/lib >/dev/null 2>&1; }
if built; then
  exec cargo "$@"
fi
cat >&2 <<EOF
vkterrain: first build on this machine: about 300 crates and shaderc's C++ (glslang and
  SPIRV-Tools, built from source: Debian's libshaderc does not link). Measured on 2 cores:
  about 24 minutes in all, most of it the C++. Progress is shown below. Later builds reuse
  it (target dir: $target).
EOF
start=$(date +%s)
(
  while sleep 30; do
    ninja_file=$(ls "$target"/debug/build/shaderc-sys-*/out/build/build.ninja 2>/dev/null | head -n1 || true)
    elapsed=$(( $(date +%s) - start ))
    if [ -n "$ninja_file" ]; then
      dir=$(dirname "$ninja_file")
      total=$(grep -c '^build [^:]*\.o:' "$ninja_file" || true)
      done_=$(find "$dir" -name '*.o' | wc -l)
      echo "vkterrain: first build, $((elapsed / 60)) min $((elapsed % 60)) s: shaderc C++ $done_ of $total objects" >&2
    else
      echo "vkterrain: first build, $((elapsed / 60)) min $((elapsed % 60)) s: compiling crates" >&2
    fi
    built && break
  done
) &
watcher=$!
trap 'kill "$watcher" 2>/dev/null || true' EXIT
cargo "$@"
