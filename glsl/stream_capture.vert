#version 450
// Test hook for streamed frames: capture.vert's placement with heights from the atlas
// (one array layer per tile) and positions relative to the anchor sample.
#extension GL_GOOGLE_include_directive : require
#define USE_BlockPush
#define USE_FrameUniforms
#define HEIGHTS_ATLAS
#include "layout.glsl"
#include "common.glsl"

layout(set = 0, binding = TERRAIN_BINDING_HEIGHTS) uniform sampler2DArray heights;
#include "block_vertex.glsl"

layout(set = 0, binding = CAPTURE_BINDING_POSITIONS, std430) writeonly buffer Captured {
    vec4 positions[];
};
layout(location = 0) in uvec2 in_local;

void main() {
    int k = frame.extent.w;
    positions[gl_InstanceIndex * k * k + gl_VertexIndex] = vec4(place_block_vertex(ivec2(in_local)), 1.0);
    gl_Position = vec4(0.0, 0.0, 0.0, 1.0);
}
