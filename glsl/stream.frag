#version 450
// Streamed frames: lit by the in-memory frame's light without shadows (`--sun off`) with
// normals from the surface's own derivatives (flat per triangle; streamed tiles bring no
// gradient map yet), coloured by the in-memory shading's ramp and water (its sea share
// from the vertices) with its procedural detail, fogged towards the horizon colour; the
// sky (sky.frag) is drawn after the blocks where none was.
#define USE_FrameUniforms
#extension GL_GOOGLE_include_directive : require
#include "layout.glsl"
#include "ramp.glsl"

layout(location = 0) in vec3 v_relative;
layout(location = 1) in vec2 v_sample;
layout(location = 2) in float v_sea;
layout(location = 3) flat in int v_lod;
layout(location = 0) out vec4 out_color;

void main() {
    if (any(greaterThan(v_sample, vec2(frame.extent.xy - 1) + 1e-3))) discard;
    vec3 n = normalize(cross(dFdy(v_relative), dFdx(v_relative)));
    if (n.y < 0.0) n = -n;
    vec3 albedo = ground_colour(v_relative.y, 1.0 - n.y, v_sea) * procedural_detail(v_sample);
    // Colour by LOD (frame.flags.y), mixed as in memory (terrain_shade.glsl).
    if (frame.flags.y != 0) {
        vec3 palette[] = LOD_PALETTE;
        albedo = mix(albedo, palette[v_lod % palette.length()], 0.6);
    }
    float lit = frame.light.w + (1.0 - frame.light.w) * max(dot(n, frame.light.xyz), 0.0);
    vec3 c = albedo * lit;
    float d = length(v_relative - frame.camera_fog.xyz);
    float fog = 1.0 - exp(-frame.camera_fog.w * d);
    out_color = vec4(mix(c, frame.sky_horizon.rgb, clamp(fog, 0.0, 1.0)), 1.0);
}
