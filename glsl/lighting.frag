#version 450
// Sun visibility and ambient occlusion per lighting texel (src/lighting.rs is the CPU
// reference and explains the method). Drawn once at load and whenever the sun moves.
#extension GL_GOOGLE_include_directive : require
#define USE_LightingPush
#include "layout.glsl"
#include "common.glsl"

layout(set = 0, binding = LIGHTING_BINDING_HEIGHTS) uniform sampler2D heights;
layout(location = 0) out vec2 out_light;

// World height of terrain sample s: the nearest sample the heights hold (every
// source.x-th: LightingSource::height_near), clamped to the image as raw_at clamps.
float height_at(ivec2 s) {
    int stride = lighting_pc.source.x;
    ivec2 t = min((s + stride / 2) / stride, textureSize(heights, 0) - 1);
    return decode_raw(texelFetch(heights, t, 0).r, lighting_pc.grid.w) * lighting_pc.params.y;
}

// Height of the sample nearest p + d t, or false outside the true extent.
bool sample_along(vec2 p, vec2 d, float t, out float h) {
    ivec2 q = ivec2(floor(p + d * t + 0.5));
    if (any(lessThan(q, ivec2(0))) || any(greaterThanEqual(q, lighting_pc.grid.xy))) return false;
    h = height_at(q);
    return true;
}

void main() {
    if (lighting_pc.sun.w == 0.0) {
        out_light = vec2(1.0);
        return;
    }
    ivec2 s = ivec2(gl_FragCoord.xy) * lighting_pc.grid.z;
    vec2 p = vec2(s);
    float h0 = height_at(s);
    vec2 spacing = lighting_pc.params.xz;

    float horizon = -3.4028235e38; // f32::MIN, as on the CPU
    float t = 1.0;
    float h;
    for (uint k = 0u; k < SUN_MAX_STEPS; k++) {
        if (!sample_along(p, lighting_pc.sun.xz, t, h)) break;
        horizon = max(horizon, (h - h0) / (t * lighting_pc.params.w));
        t += max(t * SUN_STEP_GROWTH, 1.0);
    }
    float visible = clamp(0.5 + (lighting_pc.sun.y - horizon) / (2.0 * SUN_SOFTNESS), 0.0, 1.0);

    vec2 dirs[] = AO_DIRECTIONS;
    float dists[] = AO_DISTANCES;
    float open = 0.0;
    for (int i = 0; i < dirs.length(); i++) {
        float tan_h = 0.0;
        vec2 m = dirs[i] * spacing; // metres per unit of distance along this direction
        float metres = sqrt(m.x * m.x + m.y * m.y);
        for (int j = 0; j < dists.length(); j++) {
            if (!sample_along(p, dirs[i], dists[j], h)) break;
            tan_h = max(tan_h, (h - h0) / (dists[j] * metres));
        }
        open += 1.0 - tan_h / sqrt(1.0 + tan_h * tan_h);
    }
    out_light = vec2(visible, open / float(dirs.length()));
}
