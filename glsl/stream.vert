#version 450
// Streamed frames (SPEC 8): terrain.vert's placement with heights from the atlas layer
// of the block's tile, positions relative to the anchor sample (the camera's nearest).
#extension GL_GOOGLE_include_directive : require
#define USE_BlockPush
#define USE_FrameUniforms
#define HEIGHTS_ATLAS
#include "layout.glsl"
#include "common.glsl"

layout(set = 0, binding = TERRAIN_BINDING_HEIGHTS) uniform sampler2DArray heights;
#include "block_vertex.glsl"

layout(location = 0) in uvec2 in_local;
layout(location = 0) out vec3 v_relative;
layout(location = 1) out vec2 v_sample;
// 1 at a vertex whose sample is at or below sea level (its sample's, not its morphed
// height): interpolated, the share of sea around a point (streamed tiles bring no
// per-sample flags; in memory the four samples around it).
layout(location = 2) out float v_sea;
// The block's LOD (the colour-by-LOD view).
layout(location = 3) flat out int v_lod;
// Where the point lies in its tile's atlas layer (texels, the border included: texel
// i + 1 is the tile's vertex i), and that layer and the tile's level: stream.frag takes
// the normal from the tile's heights there.
layout(location = 4) out vec2 v_texel;
layout(location = 5) flat out ivec2 v_layer_level;

void main() {
    vec3 p = place_block_vertex(ivec2(in_local));
    v_relative = p;
    // Samples from the terrain's origin, for the true-extent test (exact enough: it
    // only decides the last half sample at the far edges).
    v_sample = p.xz / frame.spacing.xy + vec2(frame.anchor.xy);
    v_sea = float(placed_sample_raw * frame.terrain.y <= frame.texturing.w);
    v_lod = block_pc.block.w;
    // Integer offsets first (the tile's origin may be far from the anchor).
    v_texel = (p.xz / frame.spacing.xy + vec2(frame.anchor.xy - block_pc.tile.xy)) / float(1 << block_pc.tile.z) + 1.0;
    v_layer_level = block_pc.tile.wz;
    gl_Position = frame.view_proj * vec4(p, 1.0);
}
