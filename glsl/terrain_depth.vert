#version 450
// The deferred shading's depth pass: terrain.vert's placement, the embedding margin
// clipped here (no fragment shader; shade.frag recovers the position from depth).
#extension GL_GOOGLE_include_directive : require
#define USE_BlockPush
#define USE_FrameUniforms
#include "layout.glsl"
#include "common.glsl"

layout(set = 0, binding = TERRAIN_BINDING_HEIGHTS) uniform sampler2D heights;
#include "block_vertex.glsl"
#include "margin.glsl"

layout(location = 0) in uvec2 in_local;
out gl_PerVertex {
    vec4 gl_Position;
    float gl_ClipDistance[2];
};

void main() {
    vec3 world = place_block_vertex(ivec2(in_local));
    vec2 inside = inside_extent(world);
    gl_ClipDistance[0] = inside.x;
    gl_ClipDistance[1] = inside.y;
    gl_Position = frame.view_proj * vec4(world, 1.0);
}
