// Block vertex placement. World position of vertex `local` of the block in `block_pc`
// (SPEC section 5): corners at their resolved heights, edge vertices next to a coarser
// block on that block's (morphed) edge, odd vertices morphed towards the parent's surface
// (src/morph.rs). Shared by terrain.vert and capture.vert (which tests it against
// quadtree::block_vertex, bit for bit). Needs `heights`, `frame` and `block_pc` declared
// by the includer.

float raw_at(ivec2 s) {
    return decode_raw(texelFetch(heights, s, 0).r, frame.flags.x);
}

// `raw` moved towards the parent surface's height `p`; factor 1 is `raw` itself.
// `precise`: no fused multiply-add, so the CPU mirror gets the same bits.
float morph_raw(float p, float raw, float f) {
    if (f >= 1.0) return raw;
    precise float m = p + (raw - p) * f;
    return m;
}

// The block's own vertex: at an odd position it lies on an edge or the a-i diagonal of
// its parent's quad, where the parent surface is the mean of the two samples around it.
float own_vertex_raw(ivec2 local, ivec2 s, int last) {
    float raw = raw_at(s);
    bool odd_u = (local.x & 1) == 1;
    bool odd_v = (local.y & 1) == 1;
    float f;
    if (local.y == 0) f = block_pc.morph_edges.x;
    else if (local.y == last) f = block_pc.morph_edges.z;
    else if (local.x == last) f = block_pc.morph_edges.y;
    else if (local.x == 0) f = block_pc.morph_edges.w;
    else f = block_pc.morph.x;
    if (!(odd_u || odd_v) || f >= 1.0) return raw;
    int st = block_pc.block.z;
    ivec2 d = ivec2(odd_u ? st : 0, odd_v ? st : 0);
    precise float p = (raw_at(s - d) + raw_at(s + d)) * 0.5;
    return morph_raw(p, raw, f);
}

// The coarser neighbour's vertex at sample s on the edge across `side` (its stride
// `best`), as that block draws it: odd vertices morph with the edge's factor, which both
// blocks are given. Its origin is a multiple of twice its stride, so parity is that of
// the coordinate over the stride.
float coarse_vertex_raw(ivec2 s, int side, int best) {
    float raw = raw_at(s);
    float f = block_pc.morph_edges[side];
    bool along_x = (side & 1) == 0;
    int coord = along_x ? s.x : s.y;
    if (((coord / best) & 1) == 0 || f >= 1.0) return raw;
    ivec2 d = along_x ? ivec2(best, 0) : ivec2(0, best);
    precise float p = (raw_at(s - d) + raw_at(s + d)) * 0.5;
    return morph_raw(p, raw, f);
}

// Corners at the start and the end of each edge (north, east, south, west).
const ivec2 EDGE_CORNERS[4] = ivec2[4](ivec2(0, 1), ivec2(1, 2), ivec2(3, 2), ivec2(0, 3));

vec3 place_block_vertex(ivec2 local) {
    int last = frame.extent.w - 1;
    int stride = block_pc.block.z;
    ivec2 s = block_pc.block.xy + local * stride;
    vec3 world = vec3(float(s.x) * frame.terrain.x, 0.0, float(s.y) * frame.terrain.x);

    int corner = -1;
    if (local == ivec2(0, 0)) corner = 0;
    else if (local == ivec2(last, 0)) corner = 1;
    else if (local == ivec2(last, last)) corner = 2;
    else if (local == ivec2(0, last)) corner = 3;
    if (corner >= 0) {
        world.y = block_pc.corner_raw[corner] * frame.terrain.y;
        return world;
    }

    // Other edge vertices next to a coarser block follow that block's edge.
    ivec4 cn = block_pc.coarser_neighbour_stride;
    int side = -1;
    if (local.y == 0 && cn.x > 0) side = 0;
    else if (local.y == last && cn.z > 0) side = 2;
    else if (local.x == last && cn.y > 0) side = 1;
    else if (local.x == 0 && cn.w > 0) side = 3;

    float raw;
    if (side < 0) {
        raw = own_vertex_raw(local, s, last);
    } else {
        int best = cn[side];
        bool along_x = (side & 1) == 0;
        int along = along_x ? local.x : local.y;
        int coord = along_x ? s.x : s.y;
        int rem = coord % best;
        if (rem == 0) {
            // A vertex of the coarser block, inside its edge.
            raw = coarse_vertex_raw(s, side, best);
        } else if (best <= last * stride) {
            // The neighbour has vertices at both ends of this edge: collapse onto the one
            // below (degenerate triangles, no T-junction).
            if (along_x) s.x -= rem; else s.y -= rem;
            raw = along * stride == rem ? block_pc.corner_raw[EDGE_CORNERS[side].x] : coarse_vertex_raw(s, side, best);
        } else {
            // The whole edge lies inside one segment of the neighbour (LODs more than m
            // apart; the traversal splits such neighbours, other block lists may not):
            // on the line between this edge's corners, which lie on that segment.
            float ca = block_pc.corner_raw[EDGE_CORNERS[side].x];
            float cb = block_pc.corner_raw[EDGE_CORNERS[side].y];
            precise float t = float(along) / float(last);
            precise float lerp = ca + (cb - ca) * t;
            raw = lerp;
        }
    }
    return vec3(float(s.x) * frame.terrain.x, raw * frame.terrain.y, float(s.y) * frame.terrain.x);
}
