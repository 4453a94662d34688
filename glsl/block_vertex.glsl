// Block vertex placement. World position of vertex `local` of the block in `block_pc` (SPEC section 5): edge
// vertices next to a coarser block follow that block's edge. Shared by terrain.vert and
// capture.vert (which tests it against quadtree::block_vertex). Needs `heights`, `frame`
// and `block_pc` declared by the includer.

float raw_at(ivec2 s) {
    return decode_raw(texelFetch(heights, s, 0).r, frame.flags.w);
}

vec3 place_block_vertex(ivec2 local) {
    int k = frame.extent.w;
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
        // `precise`: no fused multiply-add, so the CPU mirror gets the same bits.
        precise float t = float(rem) / float(best);
        precise float lerp = ra + (rb - ra) * t;
        raw = lerp;
    }
    return vec3(float(s.x) * frame.terrain.x, raw * frame.terrain.y, float(s.y) * frame.terrain.x);
}
