// The terrain's colours, shared by the in-memory shading (terrain_shade.glsl) and the
// streamed frames (stream.frag): the height ramp with rock on steep slopes and snow, water
// at sea level, and the procedural detail over the ground. Needs `frame`.

float lattice(ivec2 c) {
    uint n = uint(c.x) * 1597334677u ^ uint(c.y) * 3812015801u;
    n = (n ^ (n >> 16)) * 2246822519u;
    n ^= n >> 13;
    return float(n & 0xffffu) / 65535.0;
}

float value_noise(vec2 p) {
    ivec2 i = ivec2(floor(p));
    vec2 f = fract(p);
    f = f * f * (3.0 - 2.0 * f);
    return mix(mix(lattice(i), lattice(i + ivec2(1, 0)), f.x),
               mix(lattice(i + ivec2(0, 1)), lattice(i + ivec2(1, 1)), f.x), f.y);
}

// Procedural detail where no detail texture is given: value noise over the ground at 4
// and 16 cycles per sample spacing, faded out where a cycle spans less than a few pixels,
// so that close views are not one flat colour and far ones do not shimmer. A function of
// (x, z) in samples alone: the same for every LOD and morph.
float procedural_detail(vec2 p) {
    float fade = 1.0 - smoothstep(0.25, 1.0, length(fwidth(p)) * 16.0);
    if (fade <= 0.0) return 1.0;
    float d = 0.6 * value_noise(p * 4.0) + 0.4 * value_noise(p * 16.0);
    return 1.0 + 0.35 * (d - 0.5) * fade;
}

// The colour ramp (src/gpu/layout.rs, RAMP_*): `t` in [0, 1], steep slopes towards rock.
vec3 ramp(float t, float slope) {
    vec3 cs[] = RAMP_COLOURS;
    float st[] = RAMP_STOPS;
    vec3 c = t < st[1] ? mix(cs[0], cs[1], (t - st[0]) / (st[1] - st[0]))
                       : mix(cs[1], cs[2], clamp((t - st[1]) / (st[2] - st[1]), 0.0, 1.0));
    c = mix(c, cs[2], smoothstep(0.35, 0.7, slope));
    return mix(c, RAMP_SNOW, smoothstep(RAMP_SNOW_FROM.x, RAMP_SNOW_FROM.y, t) * (1.0 - smoothstep(0.5, 0.8, slope)));
}

// The ground's colour at world height `y` with `slope` (1 - n.y), before detail: the ramp
// over absolute heights (frame.terrain.x: metres of its top) or the terrain's range
// (terrain.zw), water where `sea`, the share of sea-level samples around the point
// (frame.texturing.w: sea level), is over one half. Blended, not tested, so that the
// shoreline is an edge that moves continuously: a step between quads flipped whole pixels
// between land and water whenever the surface under them moved by a fraction of a pixel
// (morphing, LOD changes, the camera). From one half, so that a lone sea sample stays
// dry; decided from the samples, not the drawn height, so that LOD and morphing do not
// move it across them; the drawn height only keeps coarse triangles that rise well above
// the sea dry.
vec3 ground_colour(float y, float slope, float sea) {
    // At least one sample spacing: a height recovered from depth (deferred) is off by a
    // tiny fraction of the distance, which over a flat field's zero range would pick
    // colours at random.
    float range = max(frame.terrain.w - frame.terrain.z, min(frame.spacing.x, frame.spacing.y));
    float t = frame.terrain.x > 0.0 ? clamp(y / frame.terrain.x, 0.0, 1.0)
                                    : clamp((y - frame.terrain.z) / range, 0.0, 1.0);
    float w = smoothstep(0.5, 1.0, sea);
    if (y > frame.texturing.w + 0.05 * range) w = 0.0;
    return mix(ramp(t, slope), WATER_COLOUR, w);
}
