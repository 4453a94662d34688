# Sourced by the run and test scripts: the shared Cargo target dir (outside the clone,
# so that shaderc's ~10 minute C++ build happens once per machine) and a private
# runtime dir that keeps the Vulkan loader quiet.
export CARGO_TARGET_DIR="${CARGO_TARGET_DIR:-$HOME/.cache/vkterrain/target}"
if [ -z "${XDG_RUNTIME_DIR:-}" ] || [ ! -w "${XDG_RUNTIME_DIR:-/nonexistent}" ]; then
  export XDG_RUNTIME_DIR="${TMPDIR:-/tmp}/vkterrain-runtime-$(id -u)"
  mkdir -p "$XDG_RUNTIME_DIR" && chmod 700 "$XDG_RUNTIME_DIR"
fi
[ -d "$HOME/.cargo/bin" ] && export PATH="$HOME/.cargo/bin:$PATH"
# Debian's shaderc merged into one archive by tools/install-deps.sh; when it is absent the
# shaderc crate builds its C++ from source instead.
shaderc_dir="${XDG_CACHE_HOME:-$HOME/.cache}/vkterrain/shaderc"
if [ -z "${SHADERC_LIB_DIR:-}" ] && [ -f "$shaderc_dir/libshaderc_combined.a" ]; then
  export SHADERC_LIB_DIR="$shaderc_dir"
fi
unset shaderc_dir
