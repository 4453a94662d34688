//! The min/max height pyramid and the exact deviation pyramid: what the traversal and the
//! errors activity know about each group cell without a camera.

use crate::lod::deviation::exact_deviation;
use crate::lod::heightfield::Heightfield;

/// What the traversal and the errors activity know about each group cell without a
/// camera: min/max raw heights and the exact deviation `D_L = max |H - L_L|` (strict
/// mode's world part, [`crate::lod::deviation`]). Level `L` (1..=n) has `roots << (n-L)`
/// cells along x and z, cell `(a, b)` covering samples `[2^L a, 2^L (a+1)]` in x and z,
/// both ends included. Camera-independent and immutable: the traversal's caches belong to the
/// traversal ([`crate::lod::traversal::BlockCaches`]).
#[derive(Clone, Debug)]
pub struct MinMaxPyramid {
    pub n: u32,
    /// Roots along x and z (as the heightfield's).
    pub roots: [usize; 2],
    /// `levels[L - 1]`, row-major `[min, max]`.
    pub levels: Vec<Vec<[f32; 2]>>,
    /// `dev[L - 1]`, row-major, raw height units.
    pub dev: Vec<Vec<f32>>,
}

impl MinMaxPyramid {
    pub fn build(hf: &Heightfield) -> Self {
        let n = hf.n;
        let mut levels: Vec<Vec<[f32; 2]>> = Vec::with_capacity(n as usize);
        for l in 1..=n {
            let [cells, rows] = hf.cells(l);
            let mut level = vec![[0.0f32; 2]; cells * rows];
            if l == 1 {
                for b in 0..rows {
                    for a in 0..cells {
                        let (mut lo, mut hi) = (f32::INFINITY, f32::NEG_INFINITY);
                        for dz in 0..=2 {
                            for dx in 0..=2 {
                                let v = hf.raw_at((2 * a + dx) as i64, (2 * b + dz) as i64);
                                lo = lo.min(v);
                                hi = hi.max(v);
                            }
                        }
                        level[b * cells + a] = [lo, hi];
                    }
                }
            } else {
                let prev = &levels[(l - 2) as usize];
                let pc = cells * 2;
                for b in 0..rows {
                    for a in 0..cells {
                        let mut m = [f32::INFINITY, f32::NEG_INFINITY];
                        for (cx, cz) in [(0, 0), (1, 0), (0, 1), (1, 1)] {
                            let c = prev[(2 * b + cz) * pc + 2 * a + cx];
                            m[0] = m[0].min(c[0]);
                            m[1] = m[1].max(c[1]);
                        }
                        level[b * cells + a] = m;
                    }
                }
            }
            levels.push(level);
        }
        MinMaxPyramid { n, roots: hf.roots, levels, dev: exact_deviation(hf) }
    }

    /// Cells along x and z at level `l`.
    pub fn cells(&self, l: u32) -> [usize; 2] {
        [self.roots[0] << (self.n - l), self.roots[1] << (self.n - l)]
    }

    /// `[min, max]` raw height of cell `(a, b)` at level `l` (1..=n).
    pub fn get(&self, l: u32, a: usize, b: usize) -> [f32; 2] {
        self.levels[(l - 1) as usize][b * self.cells(l)[0] + a]
    }

    /// `D_l` (raw units) of cell `(a, b)` at level `l` (1..=n).
    pub fn deviation(&self, l: u32, a: usize, b: usize) -> f32 {
        self.dev[(l - 1) as usize][b * self.cells(l)[0] + a]
    }

    /// Min and max over the whole grid.
    pub fn range(&self) -> [f32; 2] {
        let top = &self.levels[(self.n - 1) as usize];
        top.iter().fold([f32::INFINITY, f32::NEG_INFINITY], |m, c| [m[0].min(c[0]), m[1].max(c[1])])
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::lod::heightfield::test_field as field;

    #[test]
    fn minmax_pyramid_covers_inclusive_cells() {
        let hf = field(9, 9, |x, z| (x * 3 + z) as f32);
        let mm = MinMaxPyramid::build(&hf);
        assert_eq!(mm.levels.len(), 3);
        assert_eq!(mm.get(1, 0, 0), [0.0, 8.0]);
        assert_eq!(mm.get(1, 3, 3), [6.0 * 3.0 + 6.0, 32.0]);
        assert_eq!(mm.get(3, 0, 0), [0.0, 32.0]);
        for l in 1..=3 {
            for b in 0..mm.cells(l)[1] {
                for a in 0..mm.cells(l)[0] {
                    let s = 1usize << l;
                    let mut lo = f32::INFINITY;
                    let mut hi = f32::NEG_INFINITY;
                    for z in b * s..=(b + 1) * s {
                        for x in a * s..=(a + 1) * s {
                            lo = lo.min(hf.raw_at(x as i64, z as i64));
                            hi = hi.max(hf.raw_at(x as i64, z as i64));
                        }
                    }
                    assert_eq!(mm.get(l, a, b), [lo, hi]);
                }
            }
        }
    }
}
