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
    /// `(tile_quads / 32)^2` of them.
    pub tiles: HashMap<TileKey, Vec<f32>>,
}

impl TileErrors {
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
