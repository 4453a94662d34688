#version 450
// Sky behind the forward-shaded terrain (drawn last, where the depth is still clear), or
// the plain background (`--background`: frame.sky_zenith.w 0, its colour the horizon's).
#extension GL_GOOGLE_include_directive : require
#define USE_FrameUniforms
#include "layout.glsl"
#include "sky.glsl"

layout(location = 0) in vec2 v_ndc;
layout(location = 0) out vec4 out_color;

void main() {
    out_color = vec4(frame.sky_zenith.w > 0.5 ? sky_colour(v_ndc) : frame.sky_horizon.rgb, 1.0);
}
