#version 450
// The errors activity over the atlas in the paper's mode (eqs. 2-3): one fragment per
// block k LODs coarser than the tile's level L (k = tile.w: 1 for every tile, 2 and 3
// too for the top tile, whose coarser blocks no other tile holds), the largest over its
// GROUPS x GROUPS groups (GROUPS = k - 1) of each dropped vertex's interpolation error over its own distance,
// |H(v) - (H(a) + H(b)) / 2| * height_scale * kappa / max(distance(camera, v), near).
// A group of LOD L + k spans 2^k x 2^k of the tile's quads: its four corners survive, its
// five other vertices (b d e f h, 2^(k-1) apart) are dropped and each interpolates two
// corners (eq. 1), as in memory (`lod::gie`). The max with the finer levels (eq. 4) is
// taken on the CPU across the tiles shaded (`stream::errors::nested_paper_errors`).
#extension GL_GOOGLE_include_directive : require
#define USE_TileErrorsPush
#include "layout.glsl"
#include "common.glsl"

layout(set = 0, binding = TILE_ERRORS_BINDING_HEIGHTS) uniform sampler2DArray heights;
layout(location = 0) out float out_error;

// Vertex v of the tile's square (texel v + 1 of its layer: the border comes first).
float raw_at(ivec2 v) {
    return decode_raw(texelFetch(heights, ivec3(v + 1, tile_errors_pc.tile.x), 0).r, tile_errors_pc.tile.z);
}

void main() {
    int GROUPS = tile_errors_pc.shape.x;
    int stride = 1 << tile_errors_pc.tile.y;
    // A group's side in the tile's vertices, and half of it.
    int side = 1 << tile_errors_pc.tile.w;
    int half_side = side >> 1;
    ivec2 first = (ivec2(gl_FragCoord.xy) - tile_errors_pc.origin.zw) * (side * GROUPS);
    vec2 spacing = tile_errors_pc.params.xw;
    float hscale = tile_errors_pc.params.y;
    float near_d = tile_errors_pc.params.z;
    vec3 cam = tile_errors_pc.camera.xyz;
    float kappa = tile_errors_pc.camera.w;
    // Dropped vertices (b d e f h) and the two corners each interpolates, in half groups
    // from the group's corner a (eq. 1): b=(a+c)/2, d=(a+g)/2, e=(a+i)/2, f=(c+i)/2,
    // h=(g+i)/2.
    const ivec2 dropped[5] = ivec2[5](ivec2(1, 0), ivec2(0, 1), ivec2(1, 1), ivec2(2, 1), ivec2(1, 2));
    const ivec2 from_lo[5] = ivec2[5](ivec2(0, 0), ivec2(0, 0), ivec2(0, 0), ivec2(2, 0), ivec2(0, 2));
    const ivec2 from_hi[5] = ivec2[5](ivec2(2, 0), ivec2(0, 2), ivec2(2, 2), ivec2(2, 2), ivec2(2, 2));
    float worst = 0.0;
    for (int j = 0; j < GROUPS; j++) {
        for (int i = 0; i < GROUPS; i++) {
            ivec2 a = first + side * ivec2(i, j);
            for (int k = 0; k < 5; k++) {
                ivec2 v = a + dropped[k] * half_side;
                float rv = raw_at(v);
                float wie = (rv - (raw_at(a + from_lo[k] * half_side) + raw_at(a + from_hi[k] * half_side)) * 0.5) * hscale;
                // The vertex in samples from the anchor, then in world units.
                ivec2 s = tile_errors_pc.origin.xy + v * stride;
                vec3 p = vec3(float(s.x) * spacing.x, rv * hscale, float(s.y) * spacing.y);
                worst = max(worst, abs(wie) * kappa / max(length(p - cam), near_d));
            }
        }
    }
    out_error = worst;
}
