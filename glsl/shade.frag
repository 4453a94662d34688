#version 450
// Deferred terrain shading (the default): after the blocks wrote depth only, one pass
// over the target shades each pixel once, at the surface point its depth gives, or shows
// the sky (or the background) where no block was drawn. Forward shading runs the shader
// for every 2x2 quad a triangle touches, partly covered ones included; at the sizes the
// error bound gives (a few pixels a triangle) that was most of the shading work.
#extension GL_GOOGLE_include_directive : require
#define USE_FrameUniforms
#define USE_TerrainSpec
#include "layout.glsl"
#include "common.glsl"
#include "sky.glsl"
#include "terrain_shade.glsl"

layout(set = 0, binding = TERRAIN_BINDING_DEPTH) uniform sampler2D depth;
layout(location = 0) in vec2 v_ndc;
layout(location = 0) out vec4 out_color;

void main() {
    float z = texelFetch(depth, ivec2(gl_FragCoord.xy), 0).r;
    vec3 colour;
    // One unprojection for both: llvmpipe runs both sides of a branch whose condition
    // differs across its pixels, and at depth 0 this is the sky's ray (sky.glsl).
    vec4 w = frame.inv_view_proj * vec4(v_ndc, z, 1.0);
    // Reversed Z, cleared to 0: nothing drawn here.
    if (z == 0.0) {
        colour = frame.sky_zenith.w > 0.5 ? sky_colour_of(w) : frame.sky_horizon.rgb;
    } else {
        colour = shade_terrain(w.xyz / w.w, 0);
    }
    out_color = vec4(colour, 1.0);
}
