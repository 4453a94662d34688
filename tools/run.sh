#!/usr/bin/env bash
# The run command (README): installs what a fresh Debian 12 machine lacks, builds, and
# runs vkterrain with the given arguments in the caller's folder, so that relative paths
# (`--heightmap mydem.tif`, `--out x.png`) mean what the user typed. With no arguments it
# opens the viewer on the built-in terrain; without a display it renders one frame to
# vkterrain.png (in the caller's folder) instead.
set -euo pipefail
root="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
bash "$root/tools/install-deps.sh"
source "$root/tools/env.sh"
(cd "$root" && bash tools/cargo.sh build)
bin="$CARGO_TARGET_DIR/debug/vkterrain"
if [ $# -eq 0 ]; then
  if [ -n "${DISPLAY:-}${WAYLAND_DISPLAY:-}" ]; then
    exec "$bin" view
  fi
  echo "run: no display; rendering the built-in terrain to $PWD/vkterrain.png" >&2
  exec "$bin" render --out vkterrain.png
fi
exec "$bin" "$@"
