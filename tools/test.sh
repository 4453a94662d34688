#!/usr/bin/env bash
# The test command (README): installs what a fresh Debian 12 machine lacks, then checks
# formatting, lints, and runs the whole suite under Xvfb with Vulkan validation on.
set -euo pipefail
cd "$(dirname "$0")/.."
bash tools/install-deps.sh
# A private runtime dir (the Vulkan loader wants one) and the log, both removed at exit:
# the suite leaves nothing behind in /tmp.
XDG_RUNTIME_DIR=$(mktemp -d)
log=$(mktemp)
trap 'rm -rf "$XDG_RUNTIME_DIR" "$log"' EXIT
export XDG_RUNTIME_DIR
source tools/env.sh
echo "== cargo fmt --check" >&2
cargo fmt --all -- --check
echo "== cargo clippy --all-targets -- -D warnings" >&2
bash tools/cargo.sh clippy --all-targets -- -D warnings
echo "== cargo test (lavapipe, validation + synchronization validation)" >&2
# Window tests need an X server; everything else is headless.
set +e
xvfb-run -a -s "-screen 0 1280x1024x24" cargo test --no-fail-fast "$@" 2>&1 | tee "$log"
status=${PIPESTATUS[0]}
set -e
# One closing line over every test binary.
awk '/^test result:/ { for (i = 1; i <= NF; i++) { if ($i ~ /^passed;?$/) p += $(i-1); if ($i ~ /^failed;?$/) f += $(i-1) } }
     END { printf "tests: %d passed, %d failed\n", p, f }' "$log"
exit "$status"
