//! The errors activity's answer for tiles (SPEC sections 4 and 8): one generation's
//! per-block errors, as the GPU rasterized them over the atlas, and how the traversal
//! uses them at a camera that has moved since (SPEC section 5, stale data).
//!
//! A block's error from a generation is `max over its groups of D * height_scale * kappa
//! / distance(camera, group box)`: strict mode's per-group error, one distance a group,
//! before the block's own angular factor (which the traversal applies, so that the data
//! holds while the camera turns). Plain data: the GPU side is
//! [`crate::errors::atlas`].

use super::TileKey;
use crate::lod::camera::distance_to_aabb;
use crate::lod::gie::ErrorMode;
use foldhash::HashMap;
use glam::{DVec3, Vec3};

/// One finished generation of block errors.
#[derive(Clone, Debug, Default)]
pub struct TileErrors {
    /// Its number on the errors activity's timeline.
    pub generation: u64,
    /// The camera the errors were computed for (world, f64).
    pub position: DVec3,
    /// The `kappa` (pixels per unit of tangent) and the height scale (world units a raw
    /// unit: the exaggeration changes it) they were computed with.
    pub kappa: f32,
    pub height_scale: f64,
    /// The generation's GPU time, when the device has timestamps.
    pub gpu_ms: Option<f64>,
    /// Per tile shaded: the errors of the blocks of its own level, row-major,
    /// `(tile_quads / block_quads)^2` of them (strict mode; the paper's is in `paper`).
    pub tiles: HashMap<TileKey, Vec<f32>>,
    /// The mode they were computed in.
    pub mode: ErrorMode,
    /// The paper's mode: each block's error with the max over the finer levels shaded
    /// (eq. 4, [`nested_paper_errors`]), by (LOD, x, z), and whether every level under
    /// it was shaded (then it is eq. 4's whole value).
    pub paper: HashMap<(u32, u32, u32), (f32, bool)>,
}

/// Where along x in a tile's cell (`n` texels a side) the paper's blocks `k` LODs
/// coarser than the tile begin: `n >> k` a side each, one after another (`n / 2` at 0,
/// `n / 4` at `n / 2`, ...), so that the top tile's every coarser LOD fits its cell.
pub fn paper_offset(n: usize, k: u32) -> usize {
    (1..k).map(|j| n >> j).sum()
}

/// How many LODs coarser than tile `key` the paper's passes shade: one, and for the top
/// tile (level `top`) every LOD up to its single block (`n` blocks of its own level a
/// side), whose dropped vertices no other tile holds.
pub fn paper_steps(key: TileKey, top: u8, n: usize) -> u32 {
    if key.level == top {
        n.trailing_zeros()
    } else {
        1
    }
}

/// The paper's own errors (eqs. 2-3, without the finer levels) of the blocks tile `key`'s
/// cell holds, row-major with `n` texels a side ([`paper_offset`]), by (LOD, x, z).
pub fn paper_own_errors(key: TileKey, cell: &[f32], n: usize, top: u8) -> Vec<((u32, u32, u32), f32)> {
    let mut out = Vec::new();
    for k in 1..=paper_steps(key, top, n) {
        let (side, offset) = (n >> k, paper_offset(n, k));
        let lod = u32::from(key.level) + k;
        for j in 0..side {
            for i in 0..side {
                let (bx, bz) = (key.tx as usize * side + i, key.tz as usize * side + j);
                out.push(((lod, bx as u32, bz as u32), cell[j * n + offset + i]));
            }
        }
    }
    out
}

/// The paper's block errors with eq. 4's max over finer levels, from each block's `own`
/// error shaded: a block's error is the largest of its own and its descendants' (through
/// levels not shaded too), and whether every block under it was shaded. A block whose
/// own error was not shaded has none, whatever its descendants' (its dropped vertices
/// are unknown).
pub fn nested_paper_errors(own: &HashMap<(u32, u32, u32), f32>) -> HashMap<(u32, u32, u32), (f32, bool)> {
    let Some(top) = own.keys().map(|k| k.0).max() else { return HashMap::default() };
    // Level by level upward: the largest known under each block, whether or not its own
    // error is known, and how many of its children are whole (shaded, with everything
    // under them).
    let mut under: HashMap<(u32, u32, u32), (f32, bool)> = HashMap::default();
    for lod in 1..=top {
        let mut level: HashMap<(u32, u32, u32), (f32, u8)> = HashMap::default();
        for (&k, &e) in own.iter().filter(|(k, _)| k.0 == lod) {
            level.insert(k, (e, 0));
        }
        for (&(l, bx, bz), &(e, whole)) in under.iter().filter(|(k, _)| k.0 == lod - 1) {
            let parent = level.entry((l + 1, bx / 2, bz / 2)).or_insert((e, 0));
            *parent = (parent.0.max(e), parent.1 + u8::from(whole));
        }
        for (k, (e, whole_children)) in level {
            // LOD 1 blocks have nothing under them.
            let whole = own.contains_key(&k) && (lod == 1 || whole_children == 4);
            under.insert(k, (e, whole));
        }
    }
    under.retain(|k, _| own.contains_key(k));
    under
}

impl TileErrors {
    /// The generation's block errors in the in-memory dump's layout (`errors --dump`:
    /// block LODs 1 to `root_lod` in turn, each row-major over `roots << (root_lod - j)`
    /// blocks a side), `NaN` where it has none (a tile not shaded; in strict mode the
    /// top tile's blocks coarser than its level, which the tile's summary bounds; in the
    /// paper's mode a block with a level under it not shaded).
    /// `per_side`: blocks of a tile's own level along its side.
    pub fn packed(&self, root_lod: u32, roots: [usize; 2], per_side: usize) -> Vec<f32> {
        let side = |j: u32| [roots[0] << (root_lod - j), roots[1] << (root_lod - j)];
        let start = |j: u32| (1..j).map(|l| side(l)[0] * side(l)[1]).sum::<usize>();
        let mut out = vec![f32::NAN; start(root_lod + 1)];
        let mut put = |(lod, bx, bz): (u32, usize, usize), e: f32| {
            let [w, h] = side(lod);
            if (1..=root_lod).contains(&lod) && bx < w && bz < h {
                out[start(lod) + bz * w + bx] = e;
            }
        };
        match self.mode {
            ErrorMode::Strict => {
                for (key, values) in &self.tiles {
                    for (i, &e) in values.iter().enumerate() {
                        let (bx, bz) =
                            (key.tx as usize * per_side + i % per_side, key.tz as usize * per_side + i / per_side);
                        put((u32::from(key.level), bx, bz), e);
                    }
                }
            }
            // Eq. 4's whole value only: a block with levels under it not shaded holds NaN.
            ErrorMode::Paper => {
                for (&(lod, bx, bz), &(e, whole)) in &self.paper {
                    put((lod, bx as usize, bz as usize), if whole { e } else { f32::NAN });
                }
            }
        }
        out
    }

    /// The error of block `index` (row-major within its tile) of `tile`'s own level, if
    /// this generation shaded that tile.
    pub fn block(&self, tile: TileKey, index: usize) -> Option<f32> {
        self.tiles.get(&tile).and_then(|b| b.get(index)).copied()
    }
}

/// What a block's error from a generation becomes at a camera `moved` world units from
/// the one it was computed for: every group's distance shrank by at most `moved`, so the
/// error grows by at most `d / (d - moved)`, `d` the old camera's distance to the block's
/// box (no group of the block is nearer). `None` when the camera may be inside that
/// distance: the generation says nothing about the block then.
pub fn stale_factor(old_camera: Vec3, moved: f32, (min, max): (Vec3, Vec3)) -> Option<f32> {
    if moved == 0.0 {
        return Some(1.0);
    }
    let d = distance_to_aabb(old_camera, min, max);
    (d > moved).then(|| d / (d - moved))
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Eq. 4 across tiles: a block's error is the largest of its own and its descendants'
    /// shaded, through levels not shaded; one whose own error was not shaded has none.
    /// And where a tile's cell holds them.
    #[test]
    fn paper_errors_nest_over_the_finer_levels_shaded() {
        let key = |level, tx, tz| TileKey { level, tx, tz };
        // Cells of 4 texels a side: a tile gives 2 x 2 blocks one LOD coarser; the top
        // tile (level 2) also 1 block two LODs coarser, at texel 2 of its first row.
        let cell = |values: [f32; 4], extra: f32| {
            let mut c = vec![f32::NAN; 16];
            (c[0], c[1], c[4], c[5], c[2]) = (values[0], values[1], values[2], values[3], extra);
            c
        };
        let mut own: HashMap<(u32, u32, u32), f32> = HashMap::default();
        for (k, values, extra) in [
            (key(0, 0, 0), [1.0, 5.0, 2.0, 0.5], 0.0),
            (key(1, 0, 0), [3.0, 0.0, 0.0, 0.0], 0.0),
            (key(2, 0, 0), [0.25, 0.0, 0.0, 0.0], 0.125),
        ] {
            own.extend(paper_own_errors(k, &cell(values, extra), 4, 2));
        }
        assert_eq!(own.len(), 4 + 4 + 4 + 1, "{own:?}");
        assert_eq!((own[&(1, 1, 0)], own[&(1, 0, 1)], own[&(4, 0, 0)]), (5.0, 2.0, 0.125));
        let n = nested_paper_errors(&own);
        // LOD 2 block (0, 0) holds LOD 1 blocks (0..2, 0..2): its own 3, their largest 5.
        assert_eq!(n[&(2, 0, 0)], (5.0, true));
        assert_eq!(n[&(2, 1, 0)], (0.0, false), "no shaded children: its own");
        assert_eq!((n[&(3, 0, 0)], n[&(4, 0, 0)]), ((5.0, false), (5.0, false)), "through every level");
        assert_eq!(n[&(1, 1, 1)], (0.5, true));
        // Without the level-1 tile, LOD 2 blocks have no error, and LOD 3 still sees the
        // LOD 1 blocks under it.
        own.retain(|k, _| k.0 != 2);
        let n = nested_paper_errors(&own);
        assert!(!n.contains_key(&(2, 0, 0)));
        assert_eq!(n[&(3, 0, 0)], (5.0, false));
        assert_eq!(n.len(), 4 + 4 + 1);
        assert_eq!((paper_offset(8, 1), paper_offset(8, 2), paper_offset(8, 3)), (0, 4, 6));
    }

    /// The factor bounds the growth of `1 / distance` for every point of the box and
    /// every camera within `moved` of the old one (sampled), and is `None` where a camera
    /// can reach the box.
    #[test]
    fn the_stale_factor_bounds_every_point_of_the_box() {
        let (min, max) = (Vec3::new(10.0, -2.0, 4.0), Vec3::new(14.0, 3.0, 9.0));
        let old = Vec3::new(0.0, 1.0, 0.0);
        let mut worst_ratio = 0.0f32;
        for step in 1..40 {
            let moved = step as f32 * 0.25;
            let Some(f) = stale_factor(old, moved, (min, max)) else {
                assert!(moved >= distance_to_aabb(old, min, max));
                continue;
            };
            for k in 0..64 {
                let a = k as f32 * 0.7;
                let dir = Vec3::new(a.cos(), (a * 1.3).sin() * 0.5, a.sin()).normalize();
                let cam = old + dir * moved;
                for p in [min, max, (min + max) * 0.5, Vec3::new(min.x, max.y, min.z)] {
                    let before = distance_to_aabb(old, p, p);
                    let after = distance_to_aabb(cam, p, p);
                    let ratio = before / after;
                    worst_ratio = worst_ratio.max(ratio / f);
                    assert!(ratio <= f * (1.0 + 1e-5), "moved {moved}: 1/distance grew {ratio}, bound {f}");
                }
            }
        }
        // Not vacuous: some camera comes close to the bound.
        assert!(worst_ratio > 0.9, "{worst_ratio}");
        assert_eq!(stale_factor(old, 0.0, (min, max)), Some(1.0));
        assert_eq!(stale_factor(old, 100.0, (min, max)), None);
    }
}
