// The heightfield is embedded in a power-of-two grid (SPEC section 2); blocks over the
// margin beyond the true extent are drawn, but their pixels are never shown. Needs `frame`.
bool beyond_extent(vec3 world) {
    vec2 p = world.xz / frame.terrain.x;
    vec2 extent = vec2(frame.extent.xy - 1);
    return p.x > extent.x + 1e-3 || p.y > extent.y + 1e-3;
}
