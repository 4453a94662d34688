#version 450
// Streamed frames' blocks shaded as they are drawn (forward: `--pixels forward`, the
// colour-by-LOD view, `--shading heights`, holes; the default is deferred:
// stream_depth.vert, then stream_shade.frag) by stream_shade.glsl. Normals and water: by
// default as the deferred pass takes them (the held samples' gradient map) when those
// samples are the terrain's own, else from the surface's own derivatives (flat per
// triangle) and the vertices' sea share; with NORMALS_FROM_HEIGHTS (`--shading heights`)
// as in memory (terrain_shade.glsl: central differences at the four samples around the
// point, interpolated) from the heights of the tile the block is drawn from (its
// vertices, every 2^level-th sample, often finer than the block's, and its border):
// smoother, and nearer the in-memory frame, for four gathers a fragment.
#define USE_FrameUniforms
#define USE_TerrainSpec
#extension GL_GOOGLE_include_directive : require
#include "layout.glsl"
#include "common.glsl"
#include "ramp.glsl"
#include "stream_shade.glsl"

layout(set = 0, binding = TERRAIN_BINDING_HEIGHTS) uniform sampler2DArray heights;

layout(location = 0) in vec3 v_relative;
layout(location = 1) in vec2 v_sample;
layout(location = 2) in float v_sea;
layout(location = 3) flat in int v_lod;
layout(location = 4) in vec2 v_texel;
layout(location = 5) flat in ivec2 v_layer_level;
layout(location = 0) out vec4 out_color;

// World heights of the 2 x 2 texels of the point's layer from texel `t` on, in gather
// order: (t + (0, 1)), (t + (1, 1)), (t + (1, 0)), t. Past the layer's edge (only from a
// point on the tile's outer edge) the edge repeats.
vec4 heights_from(ivec2 t) {
    vec2 side = vec2(textureSize(heights, 0).xy);
    vec4 texels = textureGather(heights, vec3((vec2(t) + 1.0) / side, float(v_layer_level.x)));
    return (frame.flags.x != 0 ? round(texels * 65535.0) : texels) * frame.terrain.y;
}

// The normal at the point, as terrain_shade.glsl's, from the heights of its tile.
vec3 tile_normal() {
    ivec2 t = ivec2(floor(v_texel));
    vec2 step = frame.spacing.xy * float(1 << v_layer_level.y);
    return normal_from_gathers(heights_from(t - 1), heights_from(t + ivec2(1, -1)), heights_from(t + ivec2(-1, 1)),
                               heights_from(t + 1), v_texel - vec2(t), step);
}

// `--voids hole`: whether the point lies in a hole, by terrain_shade.glsl's rule over the
// vertices of the block's tile (the atlas's second channel is 1 at a void): the bilinear
// share of voids around it is at least one half. A block coarser than level 0 cuts its
// holes at its tile's spacing.
bool in_hole() {
    vec2 side = vec2(textureSize(heights, 0).xy);
    ivec2 t = ivec2(floor(v_texel));
    vec2 f = v_texel - vec2(t);
    vec4 h = textureGather(heights, vec3((vec2(t) + 1.0) / side, float(v_layer_level.x)), 1);
    return mix(mix(h.w, h.z, f.x), mix(h.x, h.y, f.x), f.y) >= 0.5;
}

void main() {
    if (any(greaterThan(v_sample, vec2(frame.extent.xy - 1) + 1e-3))) discard;
    if (HOLES && in_hole()) discard;
    vec3 n;
    float sea = v_sea;
    if (NORMALS_FROM_HEIGHTS) {
        n = tile_normal();
    } else if (!COARSE_GRADIENTS) {
        // The held samples are the terrain's: as the deferred pass, and memory.
        n = held_normal(v_sample, sea);
    } else {
        n = normalize(cross(dFdy(v_relative), dFdx(v_relative)));
        if (n.y < 0.0) n = -n;
    }
    out_color = vec4(streamed_colour(v_relative, v_sample, n, sea, v_lod), 1.0);
}
