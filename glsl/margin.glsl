// The heightfield is embedded in a power-of-two grid (SPEC section 2); blocks over the
// margin beyond the true extent are drawn, but their pixels are never shown. Needs `frame`.

// Distances (in samples) inside the true extent's far edges along x and z: negative
// beyond them. Linear in the world position, so that it clips exactly where the
// forward pass discards.
vec2 inside_extent(vec3 world) {
    return vec2(frame.extent.xy - 1) + 1e-3 - world.xz / frame.spacing.xy;
}

bool beyond_extent(vec3 world) {
    return any(lessThan(inside_extent(world), vec2(0.0)));
}
