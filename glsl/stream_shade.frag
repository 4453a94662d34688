#version 450
// Streamed frames' deferred shading (the default): after the blocks wrote depth only
// (stream_depth.vert), one pass over the target shades each pixel once
// (stream_shade.glsl) at the point its depth gives, or shows the sky (or the background)
// where no block was drawn. At four triangles a pixel, shading each fragment drawn
// (stream.frag) ran the shader about once a triangle.
//
// What depth does not give is recovered: the normal is the surface's own, as the
// forward pass's flat one, from the points drawn at the neighbouring pixels (on each
// axis the nearer side: across a silhouette the other lies far behind); the sea share
// is decided from the samples around the point, as memory's, from the lighting map's
// heights (every frame.spacing.w-th sample: the terrain's own up to 2049^2).
#extension GL_GOOGLE_include_directive : require
#define USE_FrameUniforms
#include "layout.glsl"
#include "common.glsl"
#include "sky.glsl"
#include "ramp.glsl"
#include "stream_shade.glsl"

layout(set = 0, binding = TERRAIN_BINDING_DEPTH) uniform sampler2D depth;
layout(set = 0, binding = STREAM_BINDING_HELD_HEIGHTS) uniform sampler2D held;
layout(location = 0) in vec2 v_ndc;
layout(location = 0) out vec4 out_color;

// The point (relative to the anchor) drawn at pixel `px` at depth `z`.
vec3 point_at(ivec2 px, float z) {
    vec2 ndc = (vec2(px) + 0.5) / vec2(textureSize(depth, 0)) * 2.0 - 1.0;
    vec4 w = frame.inv_view_proj * vec4(ndc, z, 1.0);
    return w.xyz / w.w;
}

// The surface's step from pixel `px` (its point `p`) one pixel along `axis`: to the
// neighbour after it or from the one before it, whichever point is nearer (a neighbour
// beyond the target, or showing sky, is not taken). `ok`: false when neither is.
vec3 step_along(ivec2 px, ivec2 axis, vec3 p, out bool ok) {
    ivec2 size = textureSize(depth, 0);
    ivec2 a = px + axis, b = px - axis;
    bool a_in = all(lessThan(a, size)) && all(greaterThanEqual(a, ivec2(0)));
    bool b_in = all(lessThan(b, size)) && all(greaterThanEqual(b, ivec2(0)));
    float za = a_in ? texelFetch(depth, a, 0).r : 0.0;
    float zb = b_in ? texelFetch(depth, b, 0).r : 0.0;
    vec3 after = point_at(a, za) - p;
    vec3 before = p - point_at(b, zb);
    ok = za > 0.0 || zb > 0.0;
    if (za > 0.0 && (zb == 0.0 || dot(after, after) <= dot(before, before))) return after;
    return before;
}

// The share of sea samples around the point `at` (samples from the origin): bilinear
// over the four held samples around it, as memory's over the four samples around it.
float sea_share(vec2 at) {
    vec2 q = at / frame.spacing.w;
    ivec2 i = ivec2(floor(q));
    vec2 f = q - vec2(i);
    // Texels i and i + 1 on each axis (clamped at the far edges). Gather order: (0,1),
    // (1,1), (1,0), (0,0).
    vec4 raw = textureGather(held, (vec2(i) + 1.0) / vec2(textureSize(held, 0)));
    vec4 world = (frame.flags.x != 0 ? round(raw * 65535.0) : raw) * frame.terrain.y;
    vec4 sea = vec4(lessThanEqual(world, vec4(frame.texturing.w)));
    return mix(mix(sea.w, sea.z, f.x), mix(sea.x, sea.y, f.x), f.y);
}

void main() {
    ivec2 px = ivec2(gl_FragCoord.xy);
    float z = texelFetch(depth, px, 0).r;
    // One unprojection for both, as shade.frag (llvmpipe runs both sides of a branch
    // whose condition differs across its pixels; at depth 0 this is the sky's ray).
    vec4 w = frame.inv_view_proj * vec4(v_ndc, z, 1.0);
    vec3 colour;
    // Reversed Z, cleared to 0: nothing drawn here.
    if (z == 0.0) {
        colour = frame.sky_zenith.w > 0.5 ? sky_colour_of(w) : frame.sky_horizon.rgb;
    } else {
        vec3 p = point_at(px, z);
        bool along_x, along_y;
        vec3 dx = step_along(px, ivec2(1, 0), p, along_x);
        vec3 dy = step_along(px, ivec2(0, 1), p, along_y);
        // A lone pixel between sky: facing up.
        vec3 n = along_x && along_y ? normalize(cross(dy, dx)) : vec3(0.0, 1.0, 0.0);
        if (n.y < 0.0) n = -n;
        // Integer anchor added last, as stream.vert's v_sample.
        vec2 at = p.xz / frame.spacing.xy + vec2(frame.anchor.xy);
        colour = streamed_colour(p, at, n, sea_share(at), 0);
    }
    out_color = vec4(colour, 1.0);
}
