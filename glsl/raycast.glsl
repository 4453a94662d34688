// What the ray-cast block's two stages share: heights, the min/max pyramid (raw units,
// cells with both ends included: a bound of every sample, so of every vertex the block
// draws), and the block's resolved corners.

#include "common.glsl"

layout(set = 0, binding = TERRAIN_BINDING_HEIGHTS) uniform sampler2D heights;
layout(set = 0, binding = TERRAIN_BINDING_MINMAX) uniform sampler2D minmax;

// Min/max raw height of the cell of `quads` x `quads` quads of `block` (origin x, z in
// samples, stride, LOD) whose first quad is `q`, its resolved corners included (a corner
// on a coarser neighbour's edge is drawn at that edge's height, which the samples need
// not bound).
vec2 cell_raw_range(ivec4 block, vec4 corners, ivec2 q, int quads) {
    int level = block.w + findMSB(quads);
    ivec2 s = block.xy + q * block.z;
    vec2 mm = texelFetch(minmax, s >> level, level - 1).rg;
    int last = frame.extent.w - 1;
    ivec2 q1 = q + quads;
    if (q == ivec2(0)) mm = vec2(min(mm.x, corners.x), max(mm.y, corners.x));
    if (q1.x == last && q.y == 0) mm = vec2(min(mm.x, corners.y), max(mm.y, corners.y));
    if (q1 == ivec2(last)) mm = vec2(min(mm.x, corners.z), max(mm.y, corners.z));
    if (q.x == 0 && q1.y == last) mm = vec2(min(mm.x, corners.w), max(mm.y, corners.w));
    return mm;
}

vec2 block_raw_range(ivec4 block, vec4 corners) {
    return cell_raw_range(block, corners, ivec2(0), frame.extent.w - 1);
}
