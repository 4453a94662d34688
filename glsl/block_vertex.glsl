// Block vertex placement. World position (relative to `frame.anchor`) of vertex `local` of the block in `block_pc`
// (SPEC section 5): corners at their resolved heights, edge vertices next to a coarser
// block on that block's (morphed) edge, odd vertices morphed towards the parent's surface
// (src/morph.rs). Shared by terrain.vert, terrain_depth.vert and capture.vert (which
// tests it against quadtree::block_vertex, bit for bit). Needs `heights`, `frame` and
// `block_pc` declared by the includer.

#ifndef HEIGHTS_ATLAS
float raw_at(ivec2 s) {
    return decode_raw(texelFetch(heights, s, 0).r, frame.flags.x);
}
#endif

// `raw` moved towards the parent surface's height `p`; factor 1 is `raw` itself.
// `precise`: no fused multiply-add, so the CPU mirror gets the same bits.
float morph_raw(float p, float raw, float f) {
    if (f >= 1.0) return raw;
    precise float m = p + (raw - p) * f;
    return m;
}

// Corners at the start and the end of each edge (north, east, south, west).
const ivec2 EDGE_CORNERS[4] = ivec2[4](ivec2(0, 1), ivec2(1, 2), ivec2(3, 2), ivec2(0, 3));

// Every vertex is decided first, without a fetch: either its height is given outright
// (a corner's resolved height, or a point on a line between corners), or it is the
// sample at `s` morphed with factor `f` towards the mean of the samples at `s - d` and
// `s + d` (d = 0: not morphed). The three fetches then run once. llvmpipe runs every
// side of a branch that differs between the vertices it shades together, so fetches
// inside the branches were paid for up to three times over.
// The raw height of the sample the last placed vertex stands on, before any morph or
// stitching moved it (streamed frames decide water from it, as memory decides it from
// the samples: morphing must not move the shore).
float placed_sample_raw;

vec3 place_block_vertex(ivec2 local) {
    int last = frame.extent.w - 1;
    int stride = block_pc.block.z;
    ivec2 s = block_pc.block.xy + local * stride;
    bool given = false;
    float given_raw = 0.0;
    ivec2 d = ivec2(0);
    float f = 1.0;

    int corner = -1;
    if (local == ivec2(0, 0)) corner = 0;
    else if (local == ivec2(last, 0)) corner = 1;
    else if (local == ivec2(last, last)) corner = 2;
    else if (local == ivec2(0, last)) corner = 3;

    // Other edge vertices next to a coarser block follow that block's edge.
    ivec4 cn = block_pc.coarser_neighbour_stride;
    int side = -1;
    if (local.y == 0 && cn.x > 0) side = 0;
    else if (local.y == last && cn.z > 0) side = 2;
    else if (local.x == last && cn.y > 0) side = 1;
    else if (local.x == 0 && cn.w > 0) side = 3;

    if (corner >= 0) {
        // Corners at their resolved heights.
        given = true;
        given_raw = block_pc.corner_raw[corner];
    } else if (side < 0) {
        // The block's own vertex: at an odd position it lies on an edge or the a-i
        // diagonal of its parent's quad, where the parent surface is the mean of the two
        // samples around it.
        if (local.y == 0) f = block_pc.morph_edges.x;
        else if (local.y == last) f = block_pc.morph_edges.z;
        else if (local.x == last) f = block_pc.morph_edges.y;
        else if (local.x == 0) f = block_pc.morph_edges.w;
        else f = block_pc.morph.x;
        d = ivec2((local.x & 1) == 1 ? stride : 0, (local.y & 1) == 1 ? stride : 0);
    } else {
        int best = cn[side];
        bool along_x = (side & 1) == 0;
        int along = along_x ? local.x : local.y;
        int coord = along_x ? s.x : s.y;
        int rem = coord % best;
        if (rem != 0 && best > last * stride) {
            // The whole edge lies inside one segment of the neighbour (LODs more than m
            // apart; the traversal splits such neighbours, other block lists may not):
            // on the line between this edge's corners, which lie on that segment.
            float ca = block_pc.corner_raw[EDGE_CORNERS[side].x];
            float cb = block_pc.corner_raw[EDGE_CORNERS[side].y];
            precise float t = float(along) / float(last);
            precise float lerp = ca + (cb - ca) * t;
            given = true;
            given_raw = lerp;
        } else if (rem != 0 && along * stride == rem) {
            // Collapsed onto the neighbour's vertex below, which is this edge's first
            // corner (degenerate triangles, no T-junction).
            if (along_x) s.x -= rem; else s.y -= rem;
            given = true;
            given_raw = block_pc.corner_raw[EDGE_CORNERS[side].x];
        } else {
            // A vertex of the coarser block inside its edge, this one or (collapsed) the
            // one below, as that block draws it: its odd vertices morph with the edge's
            // factor, which both blocks are given. Its origin is a multiple of twice its
            // stride, so parity is that of the coordinate over the stride.
            if (along_x) s.x -= rem; else s.y -= rem;
            f = block_pc.morph_edges[side];
            if ((((coord - rem) / best) & 1) == 1) d = along_x ? ivec2(best, 0) : ivec2(0, best);
        }
    }

#ifdef HEIGHTS_ATLAS
    // Streamed frames: `heights` is the atlas (sampler2DArray); the block's tile holds
    // every 2^level-th sample from its origin, behind a one-sample border, and s and d
    // are multiples of that spacing. The vertex's texel is found once (a vertex of the
    // block lies in its tile); its morph neighbours' are clamped into the layer: only
    // those of a coarser neighbour's edge vertex can fall outside the tile, and streamed
    // blocks never morph those edges (their factor 1 ignores them; src/stream/morph.rs).
    ivec2 t = ((s - block_pc.tile.xy) >> block_pc.tile.z) + 1;
    ivec2 dt = d >> block_pc.tile.z;
    ivec2 hi = ivec2(frame.anchor.z - 1);
    float raw = decode_raw(texelFetch(heights, ivec3(t, block_pc.tile.w), 0).r, frame.flags.x);
    float below = decode_raw(texelFetch(heights, ivec3(max(t - dt, ivec2(0)), block_pc.tile.w), 0).r, frame.flags.x);
    float above = decode_raw(texelFetch(heights, ivec3(min(t + dt, hi), block_pc.tile.w), 0).r, frame.flags.x);
#else
    float raw = raw_at(s);
    float below = raw_at(s - d), above = raw_at(s + d);
#endif
    placed_sample_raw = raw;
    precise float p = (below + above) * 0.5;
    float h = given ? given_raw : (d == ivec2(0) ? raw : morph_raw(p, raw, f));
    // Integer sample coordinates relative to the anchor before any float (SPEC 8): a
    // shared vertex gets the same bits in every block, whatever the distance to the
    // terrain's origin. In memory the anchor is 0 and this is `s * spacing`.
    ivec2 r = s - frame.anchor.xy;
    return vec3(float(r.x) * frame.spacing.x, h * frame.terrain.y, float(r.y) * frame.spacing.y);
}
