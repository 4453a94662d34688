// What the ray-cast block's two stages share: heights, the raw height ranges of a block
// and of its cells of quads, and the block's resolved corners. In memory the ranges come
// from the min/max pyramid (raw units, cells with both ends included: a bound of every
// sample, so of every vertex the block draws); over the atlas (HEIGHTS_ATLAS) a cell's is
// the block's, which comes with the block (its vertices' range, its corners included).

#include "common.glsl"

#ifdef HEIGHTS_ATLAS
layout(set = 0, binding = TERRAIN_BINDING_HEIGHTS) uniform sampler2DArray heights;

// Raw height of vertex `q` of `block`, from its tile (origin, level, layer) in the atlas.
float block_vertex_raw(ivec4 block, ivec4 tile, ivec2 q) {
    ivec2 s = block.xy + q * block.z;
    return decode_raw(texelFetch(heights, ivec3(((s - tile.xy) >> tile.z) + 1, tile.w), 0).r, frame.flags.x);
}

vec2 cell_raw_range(ivec4 block, vec4 corners, vec2 block_range, ivec2 q, int quads) {
    return block_range;
}
#else
layout(set = 0, binding = TERRAIN_BINDING_HEIGHTS) uniform sampler2D heights;
layout(set = 0, binding = TERRAIN_BINDING_MINMAX) uniform sampler2D minmax;

float block_vertex_raw(ivec4 block, ivec4 tile, ivec2 q) {
    return decode_raw(texelFetch(heights, block.xy + q * block.z, 0).r, frame.flags.x);
}

// Min/max raw height of the cell of `quads` x `quads` quads of `block` (origin x, z in
// samples, stride, LOD) whose first quad is `q`, its resolved corners included (a corner
// on a coarser neighbour's edge is drawn at that edge's height, which the samples need
// not bound).
vec2 cell_raw_range(ivec4 block, vec4 corners, vec2 block_range, ivec2 q, int quads) {
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

#endif

vec2 block_raw_range(ivec4 block, vec4 corners, vec2 block_range) {
    return cell_raw_range(block, corners, block_range, ivec2(0), frame.extent.w - 1);
}
