# Sourced by tools/profile_frames.sh and tools/thread_ticks.sh (SCRIPT: the caller's name,
# for its messages): starts `vkterrain bench "$@"` in the background, its output in a
# temporary directory `$tmp` that is removed on exit (the bench stopped first), and
# returns once the bench's frame loop has begun (its first "frames (" progress line).
# Sets `tmp` and `pid` (the bench's).
here=$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)
# shellcheck source=env.sh
source "$here/env.sh"
bin="$CARGO_TARGET_DIR/debug/vkterrain"
[ -x "$bin" ] || { echo "$SCRIPT: $bin not built (tools/cargo.sh build)" >&2; exit 2; }
tmp=$(mktemp -d)
pid=""
# Each step may fail (the bench already gone) without stopping the rest under `set -e`.
cleanup() {
    if [ -n "$pid" ]; then kill "$pid" 2>/dev/null || true; fi
    wait 2>/dev/null || true
    rm -rf "$tmp"
}
trap cleanup EXIT
export XDG_RUNTIME_DIR="$tmp/xdg"
mkdir -p "$XDG_RUNTIME_DIR"
"$bin" bench "$@" --out "$tmp/bench" >"$tmp/log" 2>&1 &
pid=$!
until grep -q "frames (" "$tmp/log" 2>/dev/null; do
    kill -0 "$pid" 2>/dev/null || { cat "$tmp/log" >&2; echo "$SCRIPT: the bench ended before its frame loop" >&2; exit 1; }
    sleep 0.2
done
