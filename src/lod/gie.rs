//! Plain-Rust reference of the group interpolation error (SPEC sections 2-3, seed 000
//! eqs. 1-4) and of its reduction to one error per drawable block. It is the oracle
//! for the GPU errors activity, and does the same f32 operations in the same order.

use crate::lod::camera::{distance_to_aabb, Camera};
use crate::lod::heightfield::Heightfield;
use crate::lod::pyramid::MinMaxPyramid;
use glam::Vec3;

/// Which error bound to compute (SPEC section 3).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Default, clap::ValueEnum, serde::Serialize)]
#[serde(rename_all = "lowercase")]
pub enum ErrorMode {
    /// The paper's eqs. 2-4: per-vertex distance, max over nested levels.
    Paper,
    /// A bound on the surface actually drawn: the exact deviation of each group from its
    /// LOD mesh over the distance to the group's box; the traversal adds the block's own
    /// 1 / cos^2 and the stitched strips.
    #[default]
    Strict,
}

impl ErrorMode {
    pub fn as_str(self) -> &'static str {
        match self {
            ErrorMode::Paper => "paper",
            ErrorMode::Strict => "strict",
        }
    }
}

/// Everything an error generation depends on besides the heightfield. Strict mode's
/// data depends on the camera's position only, not on its rotation.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ErrorParams {
    pub camera: Vec3,
    pub kappa: f32,
    pub near: f32,
    pub mode: ErrorMode,
}

impl ErrorParams {
    pub fn new(cam: &Camera, mode: ErrorMode) -> Self {
        ErrorParams { camera: cam.position, kappa: cam.kappa(), near: cam.near, mode }
    }
}

/// The world-space part of strict mode. Only [`WorldPart::Exact`] is used by the
/// renderer; the others exist to measure what it buys and to show that the audit
/// catches a bound that is too small (mutation tests).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum WorldPart {
    /// `D_i = max |H - L_i|` over the group (SPEC section 3).
    Exact,
    /// `max(children) + max |WIE|`: valid but loose (the first wave's bound).
    NestedSum,
    /// `max(children, max |WIE|)`: the paper's eq. 4 in world units; NOT a bound.
    NestedMax,
}

/// `GIE_i` for every group of every LOD `i = 1..=n`: `levels[i-1]` is row-major with
/// `roots << (n-i)` groups along x and z; group `(a, b)` is the cell `[2^i a, 2^i (a+1)]^2`.
#[derive(Clone, Debug)]
pub struct GroupErrors {
    pub n: u32,
    pub roots: [usize; 2],
    pub levels: Vec<Vec<f32>>,
}

impl GroupErrors {
    /// Groups of LOD `lod` along x and z.
    pub fn groups(&self, lod: u32) -> [usize; 2] {
        [self.roots[0] << (self.n - lod), self.roots[1] << (self.n - lod)]
    }
    pub fn get(&self, lod: u32, a: usize, b: usize) -> f32 {
        self.levels[(lod - 1) as usize][b * self.groups(lod)[0] + a]
    }
}

/// Offsets of the dropped vertices b d e f h (units of h) and the survivors each one
/// interpolates (eq. 1): b=(a+c)/2, d=(a+g)/2, e=(a+i)/2, f=(c+i)/2, h=(g+i)/2.
const DROPPED: [(i64, i64); 5] = [(1, 0), (0, 1), (1, 1), (2, 1), (1, 2)];

/// Group errors of every LOD (eqs. 1-4, or strict mode): what the GPU computes.
pub fn group_errors(hf: &Heightfield, mm: &MinMaxPyramid, p: &ErrorParams) -> GroupErrors {
    group_errors_with(hf, mm, p, WorldPart::Exact)
}

/// [`group_errors`] with a chosen world part for strict mode (see [`WorldPart`]).
pub fn group_errors_with(hf: &Heightfield, mm: &MinMaxPyramid, p: &ErrorParams, world: WorldPart) -> GroupErrors {
    let n = hf.n;
    let hscale = hf.height_scale;
    let mut levels: Vec<Vec<f32>> = Vec::with_capacity(n as usize);
    // Nested world deviations (raw units) of the previous LOD, for the mutation variants.
    let mut nested_prev: Vec<f32> = Vec::new();
    for lod in 1..=n {
        let [side, rows] = hf.cells(lod);
        let size = 1i64 << lod;
        let h = size >> 1;
        let mut level = vec![0.0f32; side * rows];
        let mut nested = vec![0.0f32; if world == WorldPart::Exact { 0 } else { side * rows }];
        for b in 0..rows {
            for a in 0..side {
                let cx = a as i64 * size;
                let cz = b as i64 * size;
                if cx >= hf.width as i64 - 1 || cz >= hf.height as i64 - 1 {
                    continue; // wholly outside the true extent
                }
                let ra = hf.raw_at(cx, cz);
                let rc = hf.raw_at(cx + 2 * h, cz);
                let rg = hf.raw_at(cx, cz + 2 * h);
                let ri = hf.raw_at(cx + 2 * h, cz + 2 * h);
                let lo = [ra, ra, ra, rc, rg];
                let hi = [rc, rg, ri, ri, ri];
                let child = |v: &[f32]| -> f32 {
                    if lod == 1 {
                        return 0.0;
                    }
                    let (ps, pa, pb) = (side * 2, 2 * a, 2 * b);
                    v[pb * ps + pa].max(v[pb * ps + pa + 1]).max(v[(pb + 1) * ps + pa]).max(v[(pb + 1) * ps + pa + 1])
                };
                level[b * side + a] = match p.mode {
                    ErrorMode::Strict => {
                        let [mn, mx] = mm.get(lod, a, b);
                        let (bmin, bmax) = hf.world_box(cx, cz, cx + size, cz + size, [mn * hscale, mx * hscale]);
                        let d = distance_to_aabb(p.camera, bmin, bmax).max(p.near);
                        let dev = match world {
                            WorldPart::Exact => mm.deviation(lod, a, b),
                            WorldPart::NestedSum | WorldPart::NestedMax => {
                                let mut max_wie = 0.0f32;
                                for (k, (ox, oz)) in DROPPED.iter().enumerate() {
                                    let rv = hf.raw_at(cx + ox * h, cz + oz * h);
                                    max_wie = max_wie.max((rv - (lo[k] + hi[k]) * 0.5).abs());
                                }
                                let c = child(&nested_prev);
                                let v = if world == WorldPart::NestedSum { c + max_wie } else { c.max(max_wie) };
                                nested[b * side + a] = v;
                                v
                            }
                        };
                        dev * hscale * p.kappa / d
                    }
                    ErrorMode::Paper => {
                        let mut e = 0.0f32;
                        for (k, (ox, oz)) in DROPPED.iter().enumerate() {
                            let (sx, sz) = (cx + ox * h, cz + oz * h);
                            let rv = hf.raw_at(sx, sz);
                            let wie = (rv - (lo[k] + hi[k]) * 0.5) * hscale;
                            let pv = hf.world_position(sx, sz, rv);
                            let d = (pv - p.camera).length().max(p.near);
                            e = e.max(wie.abs() * p.kappa / d);
                        }
                        // Eq. 4: the max with the four child groups.
                        child(levels.last().map_or(&[][..], |v| v)).max(e)
                    }
                };
            }
        }
        levels.push(level);
        nested_prev = nested;
    }
    GroupErrors { n, roots: hf.roots, levels }
}

/// One error per drawable block (`TBE`), for block LODs `j = 1..=root_lod`:
/// `levels[j-1]` is row-major with `roots << (root_lod - j)` blocks along x and z. Blocks
/// of LOD 0 have no error. The packed form (LOD 1 first, then 2, ...) is what the GPU
/// reads back.
#[derive(Clone, Debug, PartialEq)]
pub struct BlockErrors {
    pub root_lod: u32,
    pub roots: [usize; 2],
    pub levels: Vec<Vec<f32>>,
}

impl BlockErrors {
    /// Blocks of LOD `lod` along x and z.
    pub fn blocks(&self, lod: u32) -> [usize; 2] {
        [self.roots[0] << (self.root_lod - lod), self.roots[1] << (self.root_lod - lod)]
    }

    pub fn get(&self, lod: u32, bx: usize, bz: usize) -> f32 {
        self.levels[(lod - 1) as usize][bz * self.blocks(lod)[0] + bx]
    }

    /// Floats in the packed form.
    pub fn packed_len(root_lod: u32, roots: [usize; 2]) -> usize {
        (1..=root_lod).map(|j| (roots[0] * roots[1]) << (2 * (root_lod - j))).sum()
    }

    pub fn from_packed(root_lod: u32, roots: [usize; 2], data: &[f32]) -> Self {
        let mut levels = Vec::with_capacity(root_lod as usize);
        let mut at = 0;
        for j in 1..=root_lod {
            let len = (roots[0] * roots[1]) << (2 * (root_lod - j));
            levels.push(data[at..at + len].to_vec());
            at += len;
        }
        BlockErrors { root_lod, roots, levels }
    }

    pub fn packed(&self) -> Vec<f32> {
        self.levels.concat()
    }

    /// The largest error of a root block, or 0 when the roots are at LOD 0.
    pub fn root_error(&self) -> f32 {
        self.levels.last().map_or(0.0, |l| l.iter().cloned().fold(0.0, f32::max))
    }
}

/// Reduces group errors to block errors: max over the `(k-1)^2` groups a block covers.
pub fn block_errors(g: &GroupErrors, block_m: u32) -> BlockErrors {
    let root_lod = g.n - block_m;
    let groups = 1usize << block_m;
    let mut levels = Vec::with_capacity(root_lod as usize);
    for j in 1..=root_lod {
        let [side, rows] = [g.roots[0] << (root_lod - j), g.roots[1] << (root_lod - j)];
        let mut level = vec![0.0f32; side * rows];
        for bz in 0..rows {
            for bx in 0..side {
                let mut m = 0.0f32;
                for gz in 0..groups {
                    for gx in 0..groups {
                        m = m.max(g.get(j, bx * groups + gx, bz * groups + gz));
                    }
                }
                level[bz * side + bx] = m;
            }
        }
        levels.push(level);
    }
    BlockErrors { root_lod, roots: g.roots, levels }
}

/// Fragments one GPU update shades: one per group of LOD 1..=n, plus one per block.
pub fn fragments_per_update(n: u32, block_m: u32, roots: [usize; 2]) -> u64 {
    let r = (roots[0] * roots[1]) as u64;
    let groups: u64 = (1..=n).map(|i| r << (2 * (n - i))).sum();
    groups + BlockErrors::packed_len(n - block_m, roots) as u64
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::lod::heightfield::HeightFormat;

    fn hf(side: usize, f: impl Fn(usize, usize) -> f32) -> Heightfield {
        let s: Vec<f32> = (0..side * side).map(|i| f(i % side, i / side)).collect();
        Heightfield::embed("t", side, side, &s, HeightFormat::Float32, 1.0, 1.0).unwrap()
    }

    fn params(mode: ErrorMode) -> ErrorParams {
        ErrorParams { camera: Vec3::new(4.0, 20.0, 4.0), kappa: 500.0, near: 0.1, mode }
    }

    #[test]
    fn planes_have_no_error_along_the_a_i_diagonal() {
        for f in [
            |x: usize, _z: usize| x as f32 * 3.0,
            |_x: usize, z: usize| z as f32 * 2.0,
            |x: usize, z: usize| (x + z) as f32,
        ] {
            let h = hf(9, f);
            let mm = MinMaxPyramid::build(&h);
            for mode in [ErrorMode::Paper, ErrorMode::Strict] {
                let g = group_errors(&h, &mm, &params(mode));
                assert!(g.levels.iter().flatten().all(|&e| e == 0.0));
            }
        }
        // Bilinear x*z is not a plane: the a-i diagonal sees its curvature.
        let h = hf(9, |x, z| (x * z) as f32);
        let g = group_errors(&h, &MinMaxPyramid::build(&h), &params(ErrorMode::Paper));
        assert!(g.levels[0].iter().any(|&e| e > 0.0));
    }

    #[test]
    fn spike_error_matches_the_formula() {
        // A spike at (1,1) is vertex e of group (0,0) at LOD 1: IH_e = (H_a + H_i) / 2 = 0.
        let h = hf(5, |x, z| if (x, z) == (1, 1) { 10.0 } else { 0.0 });
        let mm = MinMaxPyramid::build(&h);
        let p = params(ErrorMode::Paper);
        let g = group_errors(&h, &mm, &p);
        let d = (Vec3::new(1.0, 10.0, 1.0) - p.camera).length();
        assert_eq!(g.get(1, 0, 0), 10.0 * p.kappa / d);
        assert_eq!(g.get(1, 1, 0), 0.0);
        assert_eq!(g.get(2, 0, 0), g.get(1, 0, 0)); // max with the children
        let s = group_errors(&h, &mm, &params(ErrorMode::Strict));
        assert!(s.get(2, 0, 0) >= s.get(1, 0, 0));
    }

    #[test]
    fn exact_world_part_lies_between_the_wie_and_the_nested_sum() {
        let h = hf(33, |x, z| ((x * 7 + z * 13) % 11) as f32 + ((x as f32) * 0.3).sin() * 4.0);
        let mm = MinMaxPyramid::build(&h);
        let mut ps = params(ErrorMode::Strict);
        for cam in [Vec3::new(16.0, 3.0, 16.0), Vec3::new(-50.0, 40.0, 10.0), Vec3::new(5.0, 0.5, 30.0)] {
            ps.camera = cam;
            let exact = group_errors(&h, &mm, &ps);
            let sum = group_errors_with(&h, &mm, &ps, WorldPart::NestedSum);
            let max = group_errors_with(&h, &mm, &ps, WorldPart::NestedMax);
            // LOD 1: a group's samples are its nine vertices, so all three agree (up to the
            // rounding of two ways to interpolate).
            for other in [&sum, &max] {
                for (e, o) in exact.levels[0].iter().zip(&other.levels[0]) {
                    assert!((e - o).abs() <= 1e-5 * e.abs().max(1.0), "LOD 1: {e} vs {o}");
                }
            }
            let mut tighter = 0;
            for (le, ls) in exact.levels.iter().zip(&sum.levels) {
                for (e, s) in le.iter().zip(ls) {
                    assert!(*e <= s * (1.0 + 1e-6), "exact {e} above the nested sum {s}");
                    tighter += (e < s) as usize;
                }
            }
            assert!(tighter > 0, "the exact deviation never beat the nested sum");
        }
    }

    #[test]
    fn block_errors_pack_and_reduce() {
        let h = hf(17, |x, z| ((x * 5 + z * 3) % 7) as f32);
        let g = group_errors(&h, &MinMaxPyramid::build(&h), &params(ErrorMode::Strict));
        let b = block_errors(&g, 2); // k = 5, root LOD 2
        assert_eq!(b.levels.len(), 2);
        assert_eq!(b.blocks(1), [2, 2]);
        assert_eq!(b.get(2, 0, 0), g.levels[1].iter().cloned().fold(0.0, f32::max));
        let packed = b.packed();
        assert_eq!(packed.len(), BlockErrors::packed_len(2, [1, 1]));
        assert_eq!(BlockErrors::from_packed(2, [1, 1], &packed), b);
        assert_eq!(BlockErrors::packed_len(7, [1, 1]), 5461); // n = 12, k = 33: 21,844 bytes
        assert_eq!(BlockErrors::packed_len(6, [2, 1]), 2 * 1365); // 4097 x 2049, k = 33
        assert_eq!(fragments_per_update(2, 1, [1, 1]), 4 + 1 + 1);
        assert_eq!(fragments_per_update(2, 1, [3, 2]), 6 * (4 + 1 + 1));
    }
}
