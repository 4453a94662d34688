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

// The normal at a point `f` (fractional texels) past texel t of a heightfield whose
// texels lie `step` world units apart, as terrain_shade.glsl's: the gradients at the
// four texels around it (central differences over the 4 x 4 texels those need)
// interpolated bilinearly. `a`..`d`: the world heights of the 2 x 2 texels from t - 1,
// t + (1, -1), t + (-1, 1) and t + 1 on, each in gather order ((0, 1), (1, 1), (1, 0),
// (0, 0) from its first texel).
vec3 normal_from_gathers(vec4 a, vec4 b, vec4 c, vec4 d, vec2 f, vec2 step) {
    // H(i, j) is texel t + (i - 1, j - 1): a = H(0,1) H(1,1) H(1,0) H(0,0),
    // b = H(2,1) H(3,1) H(3,0) H(2,0), c = H(0,3) H(1,3) H(1,2) H(0,2),
    // d = H(2,3) H(3,3) H(3,2) H(2,2).
    vec2 g00 = central_gradient(b.x, a.x, c.z, a.z, step); // at H(1,1)
    vec2 g10 = central_gradient(b.y, a.y, d.w, b.w, step); // at H(2,1)
    vec2 g01 = central_gradient(d.w, c.w, c.y, a.y, step); // at H(1,2)
    vec2 g11 = central_gradient(d.z, c.z, d.x, b.x, step); // at H(2,2)
    return normal_of(mix(mix(g00, g10, f.x), mix(g01, g11, f.x), f.y));
}

// What a shader needs of one sample: its gradient (central differences of world
// heights) and whether it lies at sea level. The gradient map (Heightfield::gradient_map)
// holds both in one texel: two 16-bit signed units (world gradient = units * `scale` /
// 32767), the sea flag in the lowest bit of z.
struct Sample {
    vec2 gradient;
    bool sea;
};

Sample from_texel(uint t, float scale) {
    int x_units = int(t << 16) >> 16;
    int z_units = int(t) >> 16;
    return Sample(vec2(float(x_units & ~1), float(z_units & ~1)) * (scale / 32767.0), (z_units & 1) != 0);
}

// The light on a surface of unit normal `n` (both renderers): the ambient share
// `light.w` scaled by the open sky `sun_ao.g`, the sun from `light.xyz` by its
// visibility `sun_ao.r` (the lighting map, lighting.frag).
float light_of(vec3 n, vec4 light, vec2 sun_ao) {
    return light.w * sun_ao.g + (1.0 - light.w) * max(dot(n, normalize(light.xyz)), 0.0) * sun_ao.r;
}
