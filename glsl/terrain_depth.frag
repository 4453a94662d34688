#version 450
// The deferred shading's first pass: blocks write depth only (shade.frag colours them).
#extension GL_GOOGLE_include_directive : require
#define USE_FrameUniforms
#include "layout.glsl"
#include "margin.glsl"

layout(location = 0) in vec3 v_world;

void main() {
    if (beyond_extent(v_world)) discard;
}
