//! Integer triangle geometry shared by the strict bound's strip measure
//! ([`crate::lod::stitch`]) and the audit: which samples a drawn triangle covers, exactly.

/// Barycentric interpolation of a triangle's raw heights at sample `(px, pz)` if inside.
pub fn interpolate(t: &[(i64, i64, f32); 3], px: i64, pz: i64) -> Option<f32> {
    let w = barycentric(&t.map(|p| (p.0, p.1)), px, pz)?;
    Some(weighted(w, [t[0].2, t[1].2, t[2].2]))
}

/// Barycentric weights of sample `(px, pz)` in the triangle with corners `t`, if inside
/// (edges included, decided exactly in integers); `None` for a degenerate (collapsed)
/// triangle, which covers nothing.
pub fn barycentric(t: &[(i64, i64); 3], px: i64, pz: i64) -> Option<[f64; 3]> {
    let [(x0, z0), (x1, z1), (x2, z2)] = *t;
    let det = (x1 - x0) * (z2 - z0) - (x2 - x0) * (z1 - z0);
    if det == 0 {
        return None;
    }
    let n1 = (px - x0) * (z2 - z0) - (x2 - x0) * (pz - z0);
    let n2 = (x1 - x0) * (pz - z0) - (px - x0) * (z1 - z0);
    let n0 = det - n1 - n2;
    let s = det.signum();
    if n0 * s < 0 || n1 * s < 0 || n2 * s < 0 {
        return None;
    }
    let (w1, w2) = (n1 as f64 / det as f64, n2 as f64 / det as f64);
    Some([1.0 - w1 - w2, w1, w2])
}

/// The height with weights `w` at the corners' heights `h`.
pub fn weighted(w: [f64; 3], h: [f32; 3]) -> f32 {
    (w[0] * h[0] as f64 + w[1] * h[1] as f64 + w[2] * h[2] as f64) as f32
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Samples on a triangle's edges and corners are inside, the nearest ones beyond are
    /// not, in either winding; a collapsed triangle covers nothing; the height is the
    /// plane's.
    #[test]
    fn barycentric_includes_edges_exactly() {
        let plane = |x: i64, z: i64| 2.0 * x as f32 - 3.0 * z as f32 + 5.0;
        let ccw = [(0i64, 0i64), (8, 0), (8, 8)];
        for t in [ccw, [ccw[0], ccw[2], ccw[1]]] {
            let tri = t.map(|(x, z)| (x, z, plane(x, z)));
            for (x, z) in [(0, 0), (4, 0), (8, 0), (8, 5), (3, 3), (8, 8), (5, 2)] {
                assert_eq!(interpolate(&tri, x, z), Some(plane(x, z)), "{x}, {z}");
            }
            for (x, z) in [(3, 4), (9, 0), (4, -1), (8, 9), (0, 1)] {
                assert_eq!(interpolate(&tri, x, z), None, "{x}, {z}");
            }
        }
        assert_eq!(barycentric(&[(0, 0), (4, 4), (8, 8)], 4, 4), None);
    }
}
