// Helpers shared by the terrain and errors shaders. Heights are stored raw (the file's
// units); world height = raw * height_scale, computed in the same order as the CPU.

// R16_UNORM returns raw/65535; recover the exact integer so that the GPU and the CPU
// work on bit-identical values.
float decode_raw(float texel, int unorm16) {
    return unorm16 != 0 ? round(texel * 65535.0) : texel;
}

// A sample's gradient of world height by central differences: its neighbours' world
// heights east and west, south and north, `step` world units from it along x and z.
vec2 central_gradient(float east, float west, float south, float north, vec2 step) {
    return vec2(east - west, south - north) / (2.0 * step);
}

// The unit normal of a surface whose world height has gradient `g` (x, z).
vec3 normal_of(vec2 g) {
    return normalize(vec3(-g.x, 1.0, -g.y));
}

// The light on a surface of unit normal `n` (both renderers): the ambient share
// `light.w` scaled by the open sky `sun_ao.g`, the sun from `light.xyz` by its
// visibility `sun_ao.r` (the lighting map, lighting.frag).
float light_of(vec3 n, vec4 light, vec2 sun_ao) {
    return light.w * sun_ao.g + (1.0 - light.w) * max(dot(n, normalize(light.xyz)), 0.0) * sun_ao.r;
}
