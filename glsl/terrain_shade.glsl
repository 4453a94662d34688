// Terrain shading, shared by the forward pass (terrain.frag) and the deferred one
// (shade.frag): normals from the heightfield, base and detail textures blended as in
// seed 000 eqs. 9-11 (or a height/slope ramp), a directional sun with precomputed shadows
// and ambient occlusion, and distance fog. Needs `frame` (USE_FrameUniforms) and the
// TerrainSpec constants declared by the includer.

layout(set = 0, binding = TERRAIN_BINDING_HEIGHTS) uniform sampler2D heights;
layout(set = 0, binding = TERRAIN_BINDING_BASE) uniform sampler2D base_tex;
layout(set = 0, binding = TERRAIN_BINDING_DETAIL) uniform sampler2D detail_tex;
layout(set = 0, binding = TERRAIN_BINDING_GRADIENTS) uniform usampler2D gradients;
layout(set = 0, binding = TERRAIN_BINDING_LIGHTING) uniform sampler2D lighting;

float world_height(ivec2 s) {
    s = clamp(s, ivec2(0), textureSize(heights, 0) - 1);
    return decode_raw(texelFetch(heights, s, 0).r, frame.flags.x) * frame.terrain.y;
}

// A sample's gradient and sea flag (common.glsl's Sample). By default both come from
// the gradient map, the four samples around a pixel in one gather; `--shading heights`
// computes them from five height fetches each, for comparison. The choice is a
// specialization constant: llvmpipe runs both sides of a uniform branch.
Sample from_heights(ivec2 s) {
    vec2 g = central_gradient(world_height(s + ivec2(1, 0)), world_height(s - ivec2(1, 0)),
                              world_height(s + ivec2(0, 1)), world_height(s - ivec2(0, 1)), frame.spacing.xy);
    return Sample(g, world_height(s) <= frame.texturing.w);
}

// `--voids hole`: whether the surface point `world` lies in a hole, the bilinear share of
// hole samples around it (the flag in the lowest bit of the gradient map's x unit) at
// least one half, so that a lone void cuts the quads around it.
bool in_hole(vec3 world) {
    vec2 p = world.xz / frame.spacing.xy;
    ivec2 i0 = ivec2(floor(p));
    vec2 f = p - vec2(i0);
    uvec4 t = textureGather(gradients, (vec2(i0) + 1.0) / vec2(textureSize(gradients, 0)));
    vec4 h = vec4(t & 1u); // (0,1), (1,1), (1,0), (0,0)
    return mix(mix(h.w, h.z, f.x), mix(h.x, h.y, f.x), f.y) >= 0.5;
}

// Hash of an integer lattice point to [0, 1] (integer arithmetic: the same on every GPU).
#include "ramp.glsl"

// The lit, fogged colour of the terrain surface at `world`; `lod` is the block's level
// (the colour-by-LOD view only). Derivatives (fwidth, implicit texture LOD) are taken
// across the pixel quad, which in the deferred pass may straddle two triangles.
vec3 shade_terrain(vec3 world, int lod) {
    vec2 p = world.xz / frame.spacing.xy;
    vec2 extent = vec2(frame.extent.xy - 1);

    ivec2 i0 = ivec2(floor(p));
    vec2 f = p - vec2(i0);
    Sample s00, s10, s01, s11;
    if (NORMALS_FROM_HEIGHTS) {
        s00 = from_heights(i0);
        s10 = from_heights(i0 + ivec2(1, 0));
        s01 = from_heights(i0 + ivec2(0, 1));
        s11 = from_heights(i0 + ivec2(1, 1));
    } else {
        // Texels i0 and i0 + 1 on each axis (clamped at the far edge): the coordinate is
        // midway between their centres. Gather order: (0,1), (1,1), (1,0), (0,0).
        uvec4 t = textureGather(gradients, (vec2(i0) + 1.0) / vec2(textureSize(gradients, 0)));
        s00 = from_texel(t.w, frame.texturing.z);
        s10 = from_texel(t.z, frame.texturing.z);
        s01 = from_texel(t.x, frame.texturing.z);
        s11 = from_texel(t.y, frame.texturing.z);
    }
    vec3 n = normal_of(mix(mix(s00.gradient, s10.gradient, f.x), mix(s01.gradient, s11.gradient, f.x), f.y));

    vec3 albedo;
    vec2 uv = p / max(extent, vec2(1.0));
    if (BASE_TEXTURE) {
        albedo = texture(base_tex, uv).rgb;
    } else {
        // The bilinear share of sea samples around the pixel (their flags): 1 inside a
        // quad of four sea samples.
        float sea = mix(mix(float(s00.sea), float(s10.sea), f.x), mix(float(s01.sea), float(s11.sea), f.x), f.y);
        albedo = ground_colour(world.y, 1.0 - n.y, sea);
    }
    if (DETAIL_TEXTURE) {
        vec3 detail = texture(detail_tex, uv * frame.texturing.x).rgb;
        float alpha = frame.texturing.y;
        albedo = alpha * albedo + (1.0 - alpha) * detail;
    } else {
        albedo *= procedural_detail(p);
    }
    if (COLOUR_BY_LOD) {
        vec3 palette[] = LOD_PALETTE;
        albedo = mix(albedo, palette[lod % palette.length()], 0.6);
    }
    // Sun visibility and ambient occlusion, precomputed per lighting texel (lighting.frag):
    // texel i is sample i * (grid - 1) / (texels - 1) on each axis.
    vec2 texels = vec2(textureSize(lighting, 0));
    vec2 grid = vec2(textureSize(heights, 0));
    vec2 lit = texture(lighting, (p * (texels - 1.0) / (grid - 1.0) + 0.5) / texels).rg;
    vec3 color = albedo * light_of(n, frame.light, lit);
    float dist = length(world - frame.camera_fog.xyz);
    float fog = 1.0 - exp(-frame.camera_fog.w * dist);
    return mix(color, frame.sky_horizon.rgb, fog);
}
