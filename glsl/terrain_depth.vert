#version 450
// The deferred shading's depth pass: terrain.vert's placement, with only the world
// position passed on (for the margin test; shade.frag recovers it from depth).
#extension GL_GOOGLE_include_directive : require
#define USE_BlockPush
#define USE_FrameUniforms
#include "layout.glsl"
#include "common.glsl"

layout(set = 0, binding = TERRAIN_BINDING_HEIGHTS) uniform sampler2D heights;
#include "block_vertex.glsl"

layout(location = 0) in uvec2 in_local;
layout(location = 0) out vec3 v_world;

void main() {
    v_world = place_block_vertex(ivec2(in_local));
    gl_Position = frame.view_proj * vec4(v_world, 1.0);
}
