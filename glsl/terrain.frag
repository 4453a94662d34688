#version 450
// Forward terrain shading: every fragment of every block is shaded as it is drawn
// (`--pixels forward`; the colour-by-LOD and wireframe views). See shade.frag for the
// default, which shades each visible pixel once.
#extension GL_GOOGLE_include_directive : require
#define USE_FrameUniforms
#define USE_TerrainSpec
#include "layout.glsl"
#include "common.glsl"
#include "margin.glsl"
#include "terrain_shade.glsl"

layout(location = 0) in vec3 v_world;
layout(location = 1) flat in int v_lod;
layout(location = 0) out vec4 out_color;

void main() {
    if (beyond_extent(v_world)) discard;
    if (HOLES && in_hole(v_world)) discard;
    out_color = vec4(shade_terrain(v_world, v_lod), 1.0);
}
