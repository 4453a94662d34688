# Read by CMake when cargo builds shaderc-sys (CMAKE_TOOLCHAIN_FILE, set in
# .cargo/config.toml). shaderc-sys builds glslang and SPIRV-Tools in CMake's Release
# configuration, whose default is -O3; here they only compile this project's shaders at
# build time, so -O1 serves as well and the machine's first build is much shorter. A cache
# entry set here is kept: CMake's own default only fills an empty one.
set(CMAKE_C_FLAGS_RELEASE "-O1 -DNDEBUG" CACHE STRING "Release C flags (vkterrain: shaderc at -O1)")
set(CMAKE_CXX_FLAGS_RELEASE "-O1 -DNDEBUG" CACHE STRING "Release C++ flags (vkterrain: shaderc at -O1)")
