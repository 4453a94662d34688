#version 450
// One k x k block, placed by push constants (seed 000 eqs. 5-8). Heights are fetched
// at integer sample coordinates, so a sample has the same position in every block.
#extension GL_GOOGLE_include_directive : require
#define USE_BlockPush
#define USE_FrameUniforms
#include "layout.glsl"
#include "common.glsl"

layout(set = 0, binding = TERRAIN_BINDING_HEIGHTS) uniform sampler2D heights;
layout(location = 0) in uvec2 in_local;
layout(location = 0) out vec3 v_world;
layout(location = 1) flat out int v_lod;

float raw_at(ivec2 s) {
    return decode_raw(texelFetch(heights, s, 0).r, frame.flags.w);
}

void main() {
    int k = frame.extent.w;
    ivec2 local = ivec2(in_local);
    int stride = block_pc.block.z;
    ivec2 s = block_pc.block.xy + local * stride;
    ivec4 cn = block_pc.coarser_neighbour_stride;

    // Edge vertices next to a coarser block follow that block's edge. The coarsest
    // applicable neighbour wins at corners, where two edges meet.
    int best = 0;
    int axis = 0;
    if (local.y == 0 && cn.x > best) { best = cn.x; axis = 0; }
    if (local.y == k - 1 && cn.z > best) { best = cn.z; axis = 0; }
    if (local.x == k - 1 && cn.y > best) { best = cn.y; axis = 1; }
    if (local.x == 0 && cn.w > best) { best = cn.w; axis = 1; }

    float raw;
    int coord = axis == 0 ? s.x : s.y;
    int rem = best > 0 ? coord % best : 0;
    if (rem == 0) {
        raw = raw_at(s);
    } else if (best <= (k - 1) * stride) {
        // The neighbour has vertices at both ends of this edge: collapse onto the one
        // below (degenerate triangles, no T-junction).
        if (axis == 0) s.x -= rem; else s.y -= rem;
        raw = raw_at(s);
    } else {
        // The whole edge lies inside one segment of the neighbour: put the vertex on
        // that segment.
        ivec2 sa = s;
        ivec2 sb = s;
        if (axis == 0) { sa.x -= rem; sb.x = sa.x + best; } else { sa.y -= rem; sb.y = sa.y + best; }
        float ra = raw_at(sa);
        float rb = raw_at(sb);
        raw = ra + (rb - ra) * (float(rem) / float(best));
    }
    vec3 world = vec3(float(s.x) * frame.terrain.x, raw * frame.terrain.y, float(s.y) * frame.terrain.x);
    v_world = world;
    v_lod = block_pc.block.w;
    gl_Position = frame.view_proj * vec4(world, 1.0);
}
