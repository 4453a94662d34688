#version 450
// Streamed frames' deferred shading (the default): after the blocks wrote depth only
// (stream_depth.vert), one pass over the target shades each pixel once
// (stream_shade.glsl) at the point its depth gives, or shows the sky (or the background)
// where no block was drawn. At four triangles a pixel, shading each fragment drawn
// (stream.frag) ran the shader about once a triangle.
//
// What depth does not give comes from the gradient map of the lighting map's heights,
// every frame.spacing.w-th sample (the terrain's own samples up to 2049^2), as memory
// takes it from its own gradient map: the normal (the gradients of the four held samples
// around the point, interpolated) and the sea share (the bilinear share of those at or
// below sea level), in one gather. Where those samples are too coarse for the pixel (two held ones more than two
// pixels apart: close views of terrains over 2049^2) they come from the surface as drawn
// instead: the normal from the points drawn at the neighbouring pixels, the sea from the
// drawn height.
#extension GL_GOOGLE_include_directive : require
#define USE_FrameUniforms
#define USE_TerrainSpec
#include "layout.glsl"
#include "common.glsl"
#include "sky.glsl"
#include "ramp.glsl"
#include "stream_shade.glsl"

layout(set = 0, binding = TERRAIN_BINDING_DEPTH) uniform sampler2D depth;
layout(location = 0) in vec2 v_ndc;
layout(location = 0) out vec4 out_color;

// The point (relative to the anchor) drawn at pixel `px` at depth `z`.
vec3 point_at(ivec2 px, float z) {
    vec2 ndc = (vec2(px) + 0.5) / vec2(textureSize(depth, 0)) * 2.0 - 1.0;
    vec4 w = frame.inv_view_proj * vec4(ndc, z, 1.0);
    return w.xyz / w.w;
}

// The surface's step from pixel `px` (its point `p`, `dist` from the camera) one pixel
// along `axis`: to the neighbour after it or from the one before it, whichever point is
// nearer, among those on the same surface (drawn, and not across a silhouette: within
// half of `dist` of p's distance; the terrain behind a ridge lies far beyond it).
// `ok`: false when neither neighbour is.
vec3 step_along(ivec2 px, ivec2 axis, vec3 p, float dist, out bool ok) {
    ivec2 size = textureSize(depth, 0);
    ivec2 a = px + axis, b = px - axis;
    bool a_in = all(lessThan(a, size)) && all(greaterThanEqual(a, ivec2(0)));
    bool b_in = all(lessThan(b, size)) && all(greaterThanEqual(b, ivec2(0)));
    float za = a_in ? texelFetch(depth, a, 0).r : 0.0;
    float zb = b_in ? texelFetch(depth, b, 0).r : 0.0;
    vec3 pa = point_at(a, za), pb = point_at(b, zb);
    vec3 cam = frame.camera_fog.xyz;
    bool use_a = za > 0.0 && abs(length(pa - cam) - dist) < 0.5 * dist;
    bool use_b = zb > 0.0 && abs(length(pb - cam) - dist) < 0.5 * dist;
    vec3 after = pa - p, before = p - pb;
    ok = use_a || use_b;
    if (use_a && (!use_b || dot(after, after) <= dot(before, before))) return after;
    return before;
}

// The normal of the surface as drawn at pixel `px` (point `p`): across its neighbours'
// steps; facing the camera along a missing axis (a feature one pixel wide), or wholly
// (a lone pixel).
vec3 drawn_normal(ivec2 px, vec3 p) {
    vec3 to_camera = frame.camera_fog.xyz - p;
    float dist = length(to_camera);
    to_camera /= dist;
    bool along_x, along_y;
    vec3 dx = step_along(px, ivec2(1, 0), p, dist, along_x);
    vec3 dy = step_along(px, ivec2(0, 1), p, dist, along_y);
    vec3 n = to_camera;
    if (along_x && along_y) {
        n = normalize(cross(dy, dx));
    } else if (along_x || along_y) {
        vec3 t = normalize(along_x ? dx : dy);
        n = normalize(to_camera - dot(to_camera, t) * t);
    }
    return n.y < 0.0 ? -n : n;
}

void main() {
    ivec2 px = ivec2(gl_FragCoord.xy);
    float z = texelFetch(depth, px, 0).r;
    // One unprojection for both, as shade.frag (llvmpipe runs both sides of a branch
    // whose condition differs across its pixels; at depth 0 this is the sky's ray).
    vec4 w = frame.inv_view_proj * vec4(v_ndc, z, 1.0);
    vec3 p = w.xyz / w.w;
    // Integer anchor added last, as stream.vert's v_sample.
    vec2 at = p.xz / frame.spacing.xy + vec2(frame.anchor.xy);
    // Derivatives outside the branches (beside the sky they are not finite: such pixels
    // take the held samples).
    float spanned = length(fwidth(at));
    float rise = fwidth(p.y);
    vec3 colour;
    // Reversed Z, cleared to 0: nothing drawn here.
    if (z == 0.0) {
        colour = frame.sky_zenith.w > 0.5 ? sky_colour_of(w) : frame.sky_horizon.rgb;
    } else {
        float stride = frame.spacing.w;
        // From the held samples, as memory from its own.
        float sea;
        vec3 n = held_normal(at, sea);
        // Where two held samples lie more than two pixels apart (a pixel spans under half
        // as many samples), from the surface as drawn: its normal, and water up to sea
        // level (within depth's precision there) fading out over one sample's rise above
        // it, as the share of the samples around a point fades over a sample.
        // (COARSE_GRADIENTS: a specialization constant, true when stride > 1.)
        float near = COARSE_GRADIENTS ? 1.0 - smoothstep(0.25 * stride, 0.5 * stride, spanned) : 0.0;
        if (COARSE_GRADIENTS && near > 0.0) {
            float precision_m = 1e-6 * length(p - frame.camera_fog.xyz);
            float above = p.y - frame.texturing.w - precision_m;
            float sample_rise = rise / max(spanned, 1e-6);
            float drawn_sea = clamp(1.0 - above / max(sample_rise, precision_m), 0.0, 1.0);
            n = normalize(mix(n, drawn_normal(px, p), near));
            sea = mix(sea, drawn_sea, near);
        }
        colour = streamed_colour(p, at, n, sea, 0);
    }
    out_color = vec4(colour, 1.0);
}
