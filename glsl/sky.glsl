// Sky gradient from the view ray's elevation, at normalized device coordinates `ndc`.
// Needs `frame`.
vec3 sky_colour(vec2 ndc) {
    // Under the reversed infinite projection depth 0 is the point at infinity: its
    // homogeneous coordinates (dir, 0) hold the ray itself. Unprojecting a finite depth
    // and subtracting the camera's position instead quantizes the ray in f32 far from the
    // origin (a point two near planes away, at 10^5 m), which drew the sky as bands.
    vec4 p = frame.inv_view_proj * vec4(ndc, 0.0, 1.0);
    vec3 dir = normalize(p.xyz);
    // Smooth from a little below the horizon (hidden by terrain) towards the zenith.
    float t = smoothstep(-0.05, 0.7, dir.y);
    return mix(frame.sky_horizon.rgb, frame.sky_zenith.rgb, t);
}
