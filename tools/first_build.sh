#!/usr/bin/env bash
# Measures what a newcomer waits for (README, "Run it"): the run command's first picture,
# then the test command, from an empty build folder, crate cache and merged-shaderc cache
# (the Debian packages are whatever the machine has). Prints both times and the load.
# Everything it makes lives in one temporary folder, removed at exit.
set -euo pipefail
root="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
work=$(mktemp -d)
trap 'rm -rf "$work"' EXIT
export CARGO_TARGET_DIR="$work/target" CARGO_HOME="$work/cargo-home" XDG_CACHE_HOME="$work/cache"
mkdir -p "$CARGO_HOME" "$work/user"
cp "$root/../shared/data/puget_sound/ps_height_1k.png" "$work/user/mydem.png"
cd "$work/user"
echo "load before: $(cut -d' ' -f1-3 /proc/loadavg)"
start=$(date +%s)
bash "$root/tools/run.sh" render mydem.png --out first.png >run.out 2>run.err
echo "run command: first picture in $(($(date +%s) - start)) s; load $(cut -d' ' -f1-3 /proc/loadavg)"
cd "$root"
start=$(date +%s)
status=0
bash tools/test.sh >"$work/test.out" 2>&1 || status=$?
echo "test command: exit $status in $(($(date +%s) - start)) s; load $(cut -d' ' -f1-3 /proc/loadavg)"
tail -n 1 "$work/test.out"
exit "$status"
