// Sky gradient from the view ray's elevation: `sky_colour_of` of the unprojected point at
// infinity `p` (its xyz is the ray), `sky_colour` at normalized device coordinates `ndc`.
// Needs `frame`.
vec3 sky_colour_of(vec4 p) {
    vec3 dir = normalize(p.xyz);
    // Smooth from a little below the horizon (hidden by terrain) towards the zenith.
    float t = smoothstep(-0.05, 0.7, dir.y);
    return mix(frame.sky_horizon.rgb, frame.sky_zenith.rgb, t);
}

vec3 sky_colour(vec2 ndc) {
    // Under the reversed infinite projection depth 0 is the point at infinity: its
    // homogeneous coordinates (dir, 0) hold the ray itself. Unprojecting a finite depth
    // and subtracting the camera's position instead quantizes the ray in f32 far from the
    // origin (a point two near planes away, at 10^5 m), which drew the sky as bands.
    return sky_colour_of(frame.inv_view_proj * vec4(ndc, 0.0, 1.0));
}
