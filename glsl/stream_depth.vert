#version 450
// Streamed frames' deferred shading, first pass: stream.vert's placement, depth only (no
// fragment shader: stream_shade.frag shades each pixel from its depth), the margin
// beyond the true extent's far edges clipped here where stream.frag discards it.
#extension GL_GOOGLE_include_directive : require
#define USE_BlockPush
#define USE_FrameUniforms
#define HEIGHTS_ATLAS
#include "layout.glsl"
#include "common.glsl"

layout(set = 0, binding = TERRAIN_BINDING_HEIGHTS) uniform sampler2DArray heights;
#include "block_vertex.glsl"

layout(location = 0) in uvec2 in_local;
out gl_PerVertex {
    vec4 gl_Position;
    float gl_ClipDistance[2];
};

void main() {
    vec3 p = place_block_vertex(ivec2(in_local));
    // Samples inside the far edges (negative beyond), stream.frag's test: integer
    // offsets first, as stream.vert's (the anchor may be far from the origin).
    vec2 inside = vec2(frame.extent.xy - 1 - frame.anchor.xy) + 1e-3 - p.xz / frame.spacing.xy;
    gl_ClipDistance[0] = inside.x;
    gl_ClipDistance[1] = inside.y;
    gl_Position = frame.view_proj * vec4(p, 1.0);
}
