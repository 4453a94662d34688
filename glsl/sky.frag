#version 450
// Sky gradient behind the terrain, from the view ray's elevation.
#extension GL_GOOGLE_include_directive : require
#define USE_FrameUniforms
#include "layout.glsl"

layout(location = 0) in vec2 v_ndc;
layout(location = 0) out vec4 out_color;

void main() {
    vec4 p = frame.inv_view_proj * vec4(v_ndc, 0.5, 1.0);
    vec3 dir = normalize(p.xyz / p.w - frame.camera_fog.xyz);
    // Smooth from a little below the horizon (hidden by terrain) towards the zenith.
    float t = smoothstep(-0.05, 0.7, dir.y);
    out_color = vec4(mix(frame.sky_horizon.rgb, frame.sky_zenith.rgb, t), 1.0);
}
