#version 450
// One k x k block, placed by push constants (seed 000 eqs. 5-8). Heights are fetched
// at integer sample coordinates, so a sample has the same position in every block.
#extension GL_GOOGLE_include_directive : require
#define USE_BlockPush
#define USE_FrameUniforms
#include "layout.glsl"
#include "common.glsl"

layout(set = 0, binding = TERRAIN_BINDING_HEIGHTS) uniform sampler2D heights;
#include "block_vertex.glsl"

layout(location = 0) in uvec2 in_local;
layout(location = 0) out vec3 v_world;
layout(location = 1) flat out int v_lod;

void main() {
    vec3 world = place_block_vertex(ivec2(in_local));
    v_world = world;
    v_lod = block_pc.block.w;
    gl_Position = frame.view_proj * vec4(world, 1.0);
}
