#!/usr/bin/env bash
# Where a bench run's CPU goes on lavapipe, frame loop only: samples the process with
# `perf` from the first progress line ("frames (") for SECONDS seconds and prints the share
# of samples per thread group and object: the llvmpipe-N threads rasterize and run the
# fragment shaders, the queue thread (named vkterrain, in libvulkan_lvp.so and [JIT])
# runs the vertex shaders, triangle setup and binning, and vkterrain's own code is the
# traversal and the activities. Shaders are JIT code without symbols, so one shader's share
# is found by comparing against a build that changes only that shader.
#
# Usage: tools/profile_frames.sh SECONDS BENCH_ARGS...
#   e.g. tools/profile_frames.sh 6 --heightmap fbm4097.png --spacing 1 --height-scale 0.0333333 \
#          --fovy 45 --size 1280x720 --path fly102.txt --validation off --no-fidelity
# Needs perf (linux-perf) and a built binary (tools/cargo.sh build). Nothing is left
# behind: the bench's output and perf's data go to a temporary directory.
set -euo pipefail
seconds=${1:?usage: tools/profile_frames.sh SECONDS BENCH_ARGS...}
shift
command -v perf >/dev/null || { echo "profile_frames.sh: perf is not installed (apt-get install linux-perf)" >&2; exit 2; }
SCRIPT=profile_frames.sh
# shellcheck source=bench_frames.sh
source "$(dirname "$0")/bench_frames.sh" "$@"
perf record -q -F 999 -o "$tmp/perf.data" -p "$pid" -- sleep "$seconds" >/dev/null 2>&1
wait "$pid" || { cat "$tmp/log" >&2; exit 1; }
pid=""
echo "share of CPU samples over ${seconds} s of the frame loop (thread, object):"
perf report -i "$tmp/perf.data" --no-children --sort comm,dso --stdio 2>/dev/null | grep '%' | grep -v '^#' | head -12
python3 - "$tmp/bench/summary.json" <<'PY'
import json, sys
s = json.load(open(sys.argv[1]))
print("fps %.2f, median GPU frame %.1f ms, mean triangles %d, median traversal %.1f ms"
      % (s["avg_fps"], s["median_gpu_ms"] or 0, s["mean_triangles"], s["median_traverse_ms"]))
PY
