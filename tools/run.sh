#!/usr/bin/env bash
# The run command (README): installs what a fresh Debian 12 machine lacks, builds, and
# runs vkterrain with the given arguments. With no arguments it opens the viewer on the
# built-in terrain; without a display it renders one frame to vkterrain.png instead.
set -euo pipefail
cd "$(dirname "$0")/.."
bash tools/install-deps.sh
source tools/env.sh
bash tools/cargo.sh build
bin="$CARGO_TARGET_DIR/debug/vkterrain"
if [ $# -eq 0 ]; then
  if [ -n "${DISPLAY:-}${WAYLAND_DISPLAY:-}" ]; then
    exec "$bin" view
  fi
  echo "run: no display; rendering the built-in terrain to vkterrain.png" >&2
  exec "$bin" render --out vkterrain.png
fi
exec "$bin" "$@"
