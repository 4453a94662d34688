#!/usr/bin/env bash
# The test command (README): installs what a fresh Debian 12 machine lacks, then checks
# formatting, lints, and runs the whole suite under Xvfb with Vulkan validation on.
set -euo pipefail
cd "$(dirname "$0")/.."
bash tools/install-deps.sh
source tools/env.sh
echo "== cargo fmt --check" >&2
cargo fmt --all -- --check
echo "== cargo clippy --all-targets -- -D warnings" >&2
cargo clippy --all-targets --quiet -- -D warnings
echo "== cargo test (lavapipe, validation + synchronization validation)" >&2
# Window tests need an X server; everything else is headless.
exec xvfb-run -a -s "-screen 0 1280x1024x24" cargo test "$@"
