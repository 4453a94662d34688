#version 450
// The errors activity over the atlas (SPEC 4 and 8): one fragment per block of a tile's
// own level, the largest over its QUADS x QUADS groups (QUADS = k - 1, at most 128) of strict mode's per-group error,
// D * height_scale * kappa / distance(camera, group box). A group is one quad of the
// tile's LOD mesh; its box spans the quad and the heights its samples and surface can
// take, its corners' range widened by its D (each sample lies within D of the quad).
// The block's own angular factor is applied by the traversal, so the result holds while
// the camera turns. The corners of a row of groups are kept from the row before: one
// height and one D fetched a group.
#extension GL_GOOGLE_include_directive : require
#define USE_TileErrorsPush
#include "layout.glsl"
#include "common.glsl"

layout(set = 0, binding = TILE_ERRORS_BINDING_HEIGHTS) uniform sampler2DArray heights;
layout(set = 0, binding = TILE_ERRORS_BINDING_DEVIATION) uniform sampler2DArray deviation;
layout(location = 0) out float out_error;

// The most quads a side of a block (k = 129) for the row of corners kept.
const int MOST_QUADS = 128;

// Vertex v of the tile's square (texel v + 1 of its layer: the border comes first).
float raw_at(ivec2 v) {
    return decode_raw(texelFetch(heights, ivec3(v + 1, tile_errors_pc.tile.x), 0).r, tile_errors_pc.tile.z);
}

void main() {
    int QUADS = tile_errors_pc.shape.x;
    int slot = tile_errors_pc.tile.w;
    int stride = 1 << tile_errors_pc.tile.y;
    ivec2 first = (ivec2(gl_FragCoord.xy) - tile_errors_pc.origin.zw) * QUADS;
    vec2 spacing = tile_errors_pc.params.xw;
    float hscale = tile_errors_pc.params.y;
    float near_d = tile_errors_pc.params.z;
    vec3 cam = tile_errors_pc.camera.xyz;
    float kappa = tile_errors_pc.camera.w;

    float row[MOST_QUADS + 1];
    for (int i = 0; i <= QUADS; i++) {
        row[i] = raw_at(first + ivec2(i, 0));
    }
    float worst = 0.0;
    for (int j = 0; j < QUADS; j++) {
        float west = raw_at(first + ivec2(0, j + 1));
        // The group's first corner in samples from the anchor.
        ivec2 s0 = tile_errors_pc.origin.xy + (first + ivec2(0, j)) * stride;
        for (int i = 0; i < QUADS; i++) {
            float east = raw_at(first + ivec2(i + 1, j + 1));
            float d = texelFetch(deviation, ivec3(first + ivec2(i, j), slot), 0).r;
            float lo = min(min(row[i], row[i + 1]), min(west, east)) - d;
            float hi = max(max(row[i], row[i + 1]), max(west, east)) + d;
            int sx = s0.x + i * stride;
            vec3 bmin = vec3(float(sx) * spacing.x, lo * hscale, float(s0.y) * spacing.y);
            vec3 bmax = vec3(float(sx + stride) * spacing.x, hi * hscale, float(s0.y + stride) * spacing.y);
            vec3 dv = max(max(bmin - cam, cam - bmax), vec3(0.0));
            worst = max(worst, d * hscale * kappa / max(length(dv), near_d));
            // Corner (i, j) is done with: it becomes (i, j + 1) for the next row.
            row[i] = west;
            west = east;
        }
        row[QUADS] = west;
    }
    out_error = worst;
}
