// Sky gradient from the view ray's elevation, at normalized device coordinates `ndc`.
// Needs `frame`.
vec3 sky_colour(vec2 ndc) {
    vec4 p = frame.inv_view_proj * vec4(ndc, 0.5, 1.0);
    vec3 dir = normalize(p.xyz / p.w - frame.camera_fog.xyz);
    // Smooth from a little below the horizon (hidden by terrain) towards the zenith.
    float t = smoothstep(-0.05, 0.7, dir.y);
    return mix(frame.sky_horizon.rgb, frame.sky_zenith.rgb, t);
}
