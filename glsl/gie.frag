#version 450
// Algorithm 1 (seed 000, section 3.2): one fragment per group of LOD i, stored at mip
// i-1 of the error image. Reads the heightfield and the four child groups of LOD i-1.
#extension GL_GOOGLE_include_directive : require
#define USE_GiePush
#define USE_GieSpec
#include "layout.glsl"
#include "common.glsl"

layout(set = 0, binding = GIE_BINDING_HEIGHTS) uniform sampler2D heights;
layout(set = 0, binding = GIE_BINDING_PREV) uniform sampler2D prev_gie;
layout(set = 0, binding = GIE_BINDING_MINMAX) uniform sampler2D minmax;
layout(set = 0, binding = GIE_BINDING_DEVIATION) uniform sampler2D deviation;
layout(location = 0) out float out_gie;

float raw_at(ivec2 s) {
    return decode_raw(texelFetch(heights, s, 0).r, gie_pc.level.w);
}

void main() {
    int lod = gie_pc.level.x;
    ivec2 g = ivec2(gl_FragCoord.xy);
    int size = 1 << lod;
    int h = size >> 1;
    ivec2 corner = g * size;
    // Groups wholly outside the true extent are never drawn: no error.
    if (corner.x >= gie_pc.extent.x - 1 || corner.y >= gie_pc.extent.y - 1) {
        out_gie = 0.0;
        return;
    }
    vec2 spacing = gie_pc.params.xw;
    float hscale = gie_pc.params.y;
    float near_d = gie_pc.params.z;
    vec3 cam = gie_pc.camera.xyz;
    float kappa = gie_pc.camera.w;

    // A specialization constant, not a uniform: each mode's pipeline holds only its own
    // code (llvmpipe would otherwise run both under a mask).
    if (STRICT_ERRORS) {
        // SPEC 3, strict: the exact deviation D_i of the group from its LOD mesh (computed
        // once per heightfield) over the distance to the group's box. No nesting: D_i is
        // measured against the full-resolution surface. The traversal applies the block's
        // own 1 / cos^2, so this data does not depend on the camera's rotation.
        vec2 mm = texelFetch(minmax, g, lod - 1).rg;
        vec3 bmin = vec3(float(corner.x) * spacing.x, mm.x * hscale, float(corner.y) * spacing.y);
        vec3 bmax = vec3(float(corner.x + size) * spacing.x, mm.y * hscale, float(corner.y + size) * spacing.y);
        vec3 dv = max(max(bmin - cam, cam - bmax), vec3(0.0));
        float d = max(length(dv), near_d);
        float dev = texelFetch(deviation, g, lod - 1).r;
        out_gie = dev * hscale * kappa / d;
        return;
    }

    float ra = raw_at(corner);
    float rc = raw_at(corner + ivec2(2 * h, 0));
    float rg = raw_at(corner + ivec2(0, 2 * h));
    float ri = raw_at(corner + ivec2(2 * h, 2 * h));
    // Dropped vertices b d e f h and the two survivors each interpolates (eq. 1).
    ivec2 offs[5] = ivec2[5](ivec2(1, 0), ivec2(0, 1), ivec2(1, 1), ivec2(2, 1), ivec2(1, 2));
    float lo[5] = float[5](ra, ra, ra, rc, rg);
    float hi[5] = float[5](rc, rg, ri, ri, ri);

    float level_err = 0.0;
    for (int k = 0; k < 5; k++) {
        ivec2 s = corner + offs[k] * h;
        precise float rv = raw_at(s);
        precise float wie = (rv - (lo[k] + hi[k]) * 0.5) * hscale;
        vec3 p = vec3(float(s.x) * spacing.x, rv * hscale, float(s.y) * spacing.y);
        float d = max(length(p - cam), near_d);
        level_err = max(level_err, abs(wie) * kappa / d);
    }

    float child = 0.0;
    if (lod > 1) {
        ivec2 c = g * 2;
        child = max(max(texelFetch(prev_gie, c, 0).r, texelFetch(prev_gie, c + ivec2(1, 0), 0).r),
                    max(texelFetch(prev_gie, c + ivec2(0, 1), 0).r, texelFetch(prev_gie, c + ivec2(1, 1), 0).r));
    }
    // Paper eq. 4: the max over the group and its children.
    out_gie = max(child, level_err);
}
