#!/usr/bin/env bash
# Where a bench run's wall time goes on lavapipe, frame loop only: over SECONDS seconds
# from the first progress line ("frames ("), each thread's CPU time (from
# /proc/PID/task/*/stat) as a share of one core, and the machine's idle share (from
# /proc/stat). llvmpipe rasterizes a scene only once the queue thread has binned all of it
# and the queue thread waits for that (lp_setup.c: the scene is queued, then waited for),
# so while the queue thread bins, a two-core machine has one core idle unless another
# thread takes it.
#
# Usage: tools/thread_ticks.sh SECONDS BENCH_ARGS...
#   e.g. tools/thread_ticks.sh 10 --heightmap fbm4097.png --spacing 1 --height-scale 0.0333333 \
#          --fovy 45 --size 1280x720 --path fly.txt --validation off --no-fidelity
# Needs a built binary (tools/cargo.sh build). Leaves nothing behind: the bench's output
# goes to a temporary directory, and the bench is stopped after the window.
set -euo pipefail
seconds=${1:?usage: tools/thread_ticks.sh SECONDS BENCH_ARGS...}
shift
SCRIPT=thread_ticks.sh
# shellcheck source=bench_frames.sh
source "$(dirname "$0")/bench_frames.sh" "$@"
# Per thread: id, name, user + system ticks.
snap() { for t in /proc/"$pid"/task/*; do awk '{ sub(/^[^(]*\(/, ""); n = $0; sub(/\).*/, "", n); sub(/^[^)]*\) /, ""); print n, $12 + $13 }' "$t/stat" | sed "s/^/$(basename "$t") /"; done | sort; }
machine() { awk '/^cpu /{ print $2 + $3 + $4 + $7 + $8, $5 + $6 }' /proc/stat; }
snap >"$tmp/t0"; read -r busy0 idle0 < <(machine)
sleep "$seconds"
snap >"$tmp/t1"; read -r busy1 idle1 < <(machine)
kill -0 "$pid" 2>/dev/null || { echo "thread_ticks.sh: the bench ended inside the window; give fewer seconds" >&2; exit 1; }
hz=$(getconf CLK_TCK)
echo "over ${seconds} s of the frame loop: CPU time per thread, as a share of one core"
# Threads that inherit the process's name are told apart by id; the main thread's id is
# the process's.
join "$tmp/t0" "$tmp/t1" | awk -v s="$seconds" -v hz="$hz" -v main="$pid" '{ d = $NF - $3; if (d > 0) printf "  %-8s %-16s %5.1f %%%s\n", $1, $2, 100 * d / (s * hz), ($1 == main ? "  (main thread)" : "") }'
awk -v b="$((busy1 - busy0))" -v i="$((idle1 - idle0))" 'BEGIN { printf "machine idle: %.1f %% of %d cores\n", 100 * i / (b + i), '"$(nproc)"' }'
