//! The camera-independent part of strict mode (SPEC section 3): the exact deviation of
//! each group from the mesh that is drawn, `D_i(group) = max over the group's samples of
//! |H - L_i|`, `L_i` the LOD-i mesh split along the a-i diagonal. A group of LOD `i` is
//! exactly one quad of `L_i`, so `D_i` needs only the quad's four corners and the samples
//! it covers: `n` passes over the samples in all, computed in parallel once per
//! heightfield.

use crate::lod::heightfield::Heightfield;

/// Height of the quad `[0, s]^2` with corners `ra (0,0)`, `rc (s,0)`, `rg (0,s)`,
/// `ri (s,s)` at local sample `(lx, lz)`, split along the a-i diagonal: triangle a-c-i
/// where `lx >= lz`, a-i-g elsewhere.
#[inline]
pub fn quad_surface(ra: f32, rc: f32, rg: f32, ri: f32, inv_s: f32, lx: i64, lz: i64) -> f32 {
    let (fx, fz) = (lx as f32 * inv_s, lz as f32 * inv_s);
    if lx >= lz {
        ra + (rc - ra) * fx + (ri - rc) * fz
    } else {
        ra + (rg - ra) * fz + (ri - rg) * fx
    }
}

/// `D_l` (raw height units) for every level `l = 1..=n`: `levels[l-1]` is row-major with
/// `hf.cells(l)` groups along x and z. Groups wholly outside the true extent are 0 (never drawn).
pub fn exact_deviation(hf: &Heightfield) -> Vec<Vec<f32>> {
    (1..=hf.n).map(|l| level_deviation(hf, l)).collect()
}

fn level_deviation(hf: &Heightfield, l: u32) -> Vec<f32> {
    let [cx, cz] = hf.cells(l);
    let mut level = vec![0.0f32; cx * cz];
    let threads = std::thread::available_parallelism().map_or(1, |t| t.get()).min(cz);
    let rows_per = cz.div_ceil(threads);
    std::thread::scope(|scope| {
        for (t, chunk) in level.chunks_mut(rows_per * cx).enumerate() {
            scope.spawn(move || {
                for (r, row) in chunk.chunks_mut(cx).enumerate() {
                    let b = t * rows_per + r;
                    for (a, out) in row.iter_mut().enumerate() {
                        *out = group_deviation(hf, l, a, b);
                    }
                }
            });
        }
    });
    level
}

/// `max |H - L_l|` over the samples of group `(a, b)` of level `l`, edges included.
fn group_deviation(hf: &Heightfield, l: u32, a: usize, b: usize) -> f32 {
    let s = 1i64 << l;
    let (cx, cz) = (a as i64 * s, b as i64 * s);
    if cx >= hf.width as i64 - 1 || cz >= hf.height as i64 - 1 {
        return 0.0;
    }
    let side = hf.grid()[0];
    // Rows of the grid are contiguous: index them directly (the group lies inside).
    square_deviation(
        |x, z, count| &hf.raw[z as usize * side + x as usize..][..count],
        cx,
        cz,
        s,
        [hf.raw_at(cx, cz), hf.raw_at(cx + s, cz), hf.raw_at(cx, cz + s), hf.raw_at(cx + s, cz + s)],
        (cx, cz),
        s,
    )
}

/// `max |H - L|` over the samples `x0..=x0+span`, `z0..=z0+span` (read a row at a time
/// by `row(x, z, count)`), `L` the quad `[qx, qx + s] x [qz, qz + s]` with corner heights
/// `[a, c, g, i]` split along its a-i diagonal: the one loop behind every `D_l`, the
/// group's own samples (`span = s`) or part of them (a tile of `prepare` inside a coarser
/// group).
pub fn square_deviation<'a>(
    row: impl Fn(i64, i64, usize) -> &'a [f32],
    x0: i64,
    z0: i64,
    span: i64,
    [ra, rc, rg, ri]: [f32; 4],
    (qx, qz): (i64, i64),
    s: i64,
) -> f32 {
    let inv_s = 1.0 / s as f32;
    let mut m = 0.0f32;
    for z in z0..=z0 + span {
        for (i, &h) in row(x0, z, span as usize + 1).iter().enumerate() {
            let surface = quad_surface(ra, rc, rg, ri, inv_s, x0 + i as i64 - qx, z - qz);
            m = m.max((h - surface).abs());
        }
    }
    m
}

#[cfg(test)]
mod tests {
    use super::*;

    fn field(side: usize, f: impl Fn(usize, usize) -> f32) -> Heightfield {
        crate::lod::heightfield::test_field(side, side, f)
    }

    /// Independent oracle: barycentric interpolation over the two triangles with f64,
    /// point-in-triangle tests instead of the diagonal rule.
    fn naive(hf: &Heightfield, l: u32, a: usize, b: usize) -> f64 {
        let s = 1i64 << l;
        let (cx, cz) = (a as i64 * s, b as i64 * s);
        let p = |x: i64, z: i64| (x as f64, z as f64, hf.raw_at(x, z) as f64);
        let (pa, pc, pg, pi) = (p(cx, cz), p(cx + s, cz), p(cx, cz + s), p(cx + s, cz + s));
        let mut m = 0.0f64;
        for z in cz..=cz + s {
            for x in cx..=cx + s {
                let mut found = None;
                for t in [[pa, pc, pi], [pa, pi, pg]] {
                    let det = (t[1].0 - t[0].0) * (t[2].1 - t[0].1) - (t[2].0 - t[0].0) * (t[1].1 - t[0].1);
                    let w1 = ((x as f64 - t[0].0) * (t[2].1 - t[0].1) - (t[2].0 - t[0].0) * (z as f64 - t[0].1)) / det;
                    let w2 = ((t[1].0 - t[0].0) * (z as f64 - t[0].1) - (x as f64 - t[0].0) * (t[1].1 - t[0].1)) / det;
                    let w0 = 1.0 - w1 - w2;
                    if w0 >= -1e-12 && w1 >= -1e-12 && w2 >= -1e-12 {
                        found = Some(w0 * t[0].2 + w1 * t[1].2 + w2 * t[2].2);
                        break;
                    }
                }
                m = m.max((hf.raw_at(x, z) as f64 - found.expect("sample inside its quad")).abs());
            }
        }
        m
    }

    #[test]
    fn matches_the_naive_oracle_on_every_group() {
        let hf = field(33, |x, z| ((x * 7 + z * 13) % 11) as f32 + ((x as f32) * 0.3).sin() * 4.0);
        let d = exact_deviation(&hf);
        for l in 1..=hf.n {
            let [cx, cz] = hf.cells(l);
            for b in 0..cz {
                for a in 0..cx {
                    let want = naive(&hf, l, a, b);
                    let got = d[(l - 1) as usize][b * cx + a] as f64;
                    assert!((got - want).abs() <= 1e-4 * want.max(1.0), "level {l} group ({a},{b}): {got} vs {want}");
                }
            }
        }
    }

    #[test]
    fn planes_are_exact_and_the_a_i_diagonal_matters() {
        let plane = field(17, |x, z| 3.0 * x as f32 - 2.0 * z as f32);
        assert!(exact_deviation(&plane).iter().flatten().all(|&e| e < 1e-4));
        // x*z is bilinear: the edge samples b, d, f, h lie on the quad's triangles, the
        // centre e = 1 sits below the a-i diagonal's midpoint (0 + 4) / 2.
        let saddle = field(3, |x, z| (x * z) as f32);
        assert_eq!(exact_deviation(&saddle)[0][0], 1.0);
    }

    #[test]
    fn a_spike_is_seen_at_every_level_above_it() {
        let hf = field(17, |x, z| if (x, z) == (5, 9) { 8.0 } else { 0.0 });
        let d = exact_deviation(&hf);
        for l in 1..=hf.n {
            let side = hf.cells(l)[0];
            let (a, b) = (5 >> l, 9 >> l);
            assert_eq!(d[(l - 1) as usize][b * side + a], 8.0, "level {l}");
        }
    }
}
