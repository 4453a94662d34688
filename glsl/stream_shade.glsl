// Streamed frames' colour of a surface point, shared by the forward pass (stream.frag)
// and the deferred one (stream_shade.frag): the in-memory shading's ramp and water (its
// sea share from the vertices) with its procedural detail, lit by the in-memory frame's
// light with its sun shadows and ambient occlusion from a lighting map made as in memory
// (lighting.frag) with one texel every frame.spacing.z samples (from the tiles of one
// level: draw/streamed.rs), fogged towards the horizon colour; with a base texture
// (stretched over the terrain) and a detail texture (repeated frame.texturing.x times
// across it, weighted frame.texturing.y against it) as in memory (terrain_shade.glsl).
// Needs `frame` (USE_FrameUniforms), the TerrainSpec constants (USE_TerrainSpec) and
// ramp.glsl.

layout(set = 0, binding = TERRAIN_BINDING_LIGHTING) uniform sampler2D lighting;
layout(set = 0, binding = TERRAIN_BINDING_GRADIENTS) uniform usampler2D gradients;

// The normal and the sea share at the point `at` (samples from the terrain's origin) from
// the gradient map of the lighting map's heights (every frame.spacing.w-th sample), as
// memory takes them from its own gradient map (terrain_shade.glsl): the gradients of the
// four held samples around the point interpolated, and the bilinear share of those at or
// below sea level, in one gather.
vec3 held_normal(vec2 at, out float sea) {
    vec2 q = at / frame.spacing.w;
    ivec2 t = ivec2(floor(q));
    vec2 f = q - vec2(t);
    // Gather order: (0,1), (1,1), (1,0), (0,0) from t (clamped at the far edge).
    uvec4 g = textureGather(gradients, (vec2(t) + 1.0) / vec2(textureSize(gradients, 0)));
    Sample s00 = from_texel(g.w, frame.texturing.z), s10 = from_texel(g.z, frame.texturing.z);
    Sample s01 = from_texel(g.x, frame.texturing.z), s11 = from_texel(g.y, frame.texturing.z);
    sea = mix(mix(float(s00.sea), float(s10.sea), f.x), mix(float(s01.sea), float(s11.sea), f.x), f.y);
    return normal_of(mix(mix(s00.gradient, s10.gradient, f.x), mix(s01.gradient, s11.gradient, f.x), f.y));
}
layout(set = 0, binding = TERRAIN_BINDING_BASE) uniform sampler2D base_tex;
layout(set = 0, binding = TERRAIN_BINDING_DETAIL) uniform sampler2D detail_tex;

// `relative`: the point from the anchor sample (y: its world height); `at`: the point in
// samples from the terrain's origin; `n`: its unit normal; `sea`: its share of sea;
// `lod`: its block's LOD (the colour-by-LOD view, frame.flags.y).
vec3 streamed_colour(vec3 relative, vec2 at, vec3 n, float sea, int lod) {
    vec2 uv = at / max(vec2(frame.extent.xy - 1), vec2(1.0));
    vec3 albedo = BASE_TEXTURE ? texture(base_tex, uv).rgb : ground_colour(relative.y, 1.0 - n.y, sea);
    if (DETAIL_TEXTURE) {
        float alpha = frame.texturing.y;
        albedo = alpha * albedo + (1.0 - alpha) * texture(detail_tex, uv * frame.texturing.x).rgb;
    } else {
        albedo *= procedural_detail(at);
    }
    // Mixed as in memory (terrain_shade.glsl).
    if (frame.flags.y != 0) {
        vec3 palette[] = LOD_PALETTE;
        albedo = mix(albedo, palette[lod % palette.length()], 0.6);
    }
    // Texel i of the lighting map is terrain sample i * frame.spacing.z.
    vec2 texels = vec2(textureSize(lighting, 0));
    vec2 sun_ao = texture(lighting, (at / frame.spacing.z + 0.5) / texels).rg;
    vec3 c = albedo * light_of(n, frame.light, sun_ao);
    float d = length(relative - frame.camera_fog.xyz);
    float fog = 1.0 - exp(-frame.camera_fog.w * d);
    return mix(c, frame.sky_horizon.rgb, clamp(fog, 0.0, 1.0));
}
