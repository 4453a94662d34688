//! The traversal over resident tiles (SPEC section 8, "The bound under streaming" and
//! "Precision"). Positions are f64 in the world; the camera is re-expressed relative to
//! its nearest sample (an integer), so every box handed to the f32 camera code is small
//! and exact whatever the distance to the terrain's origin.
//!
//! A block splits while its error exceeds delta, as in memory ([`crate::lod::traversal`],
//! strict mode's block bound: `D * height_scale * world_to_pixels`). Where it should
//! split but the finer tile is not held, it is drawn as it is, the tile is wanted with
//! the block's error / delta as its priority, and the block counts over the bound. Blocks
//! within the bound but above `prefetch * delta` want their finer tile too, at a lower
//! priority, so that it is there before it is needed.

use super::cache::{root_lod, serving_tile, HostCache, BLOCK_QUADS};
use super::{Grid, TileKey};
use crate::lod::camera::{world_to_pixels, Camera};
use glam::{DVec3, Vec3};

/// A camera in the world (f64 position).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct View {
    pub position: DVec3,
    /// Unit view direction.
    pub forward: Vec3,
    /// Vertical field of view, radians.
    pub fovy: f32,
    pub width: u32,
    pub height: u32,
    pub near: f32,
}

impl View {
    pub fn look_at(position: DVec3, target: DVec3, fovy_deg: f32, width: u32, height: u32, near: f32) -> Self {
        let forward = (target - position).try_normalize().unwrap_or(DVec3::NEG_Z).as_vec3();
        View { position, forward, fovy: fovy_deg.to_radians(), width, height, near }
    }

    /// The sample nearest the camera (the origin of the relative frame) and the camera
    /// relative to it.
    pub fn relative(&self, grid: &Grid) -> ([i64; 2], Camera) {
        let [sx, sz] = grid.sample_of(self.position.x, self.position.z);
        let anchor = [sx.round() as i64, sz.round() as i64];
        let [wx, wz] = grid.world_xz(anchor[0] as f64, anchor[1] as f64);
        let position = Vec3::new((self.position.x - wx) as f32, self.position.y as f32, (self.position.z - wz) as f32);
        let cam = Camera {
            position,
            forward: self.forward,
            fovy: self.fovy,
            width: self.width,
            height: self.height,
            near: self.near,
        };
        (anchor, cam)
    }
}

/// A block the frame draws.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Selected {
    pub lod: u32,
    pub bx: u32,
    pub bz: u32,
    /// The tile its vertices come from.
    pub tile: TileKey,
    /// Its error bound, pixels.
    pub error_px: f32,
    /// It should split but its finer tile is not held.
    pub over: bool,
}

/// One frame's selection.
#[derive(Clone, Debug, Default)]
pub struct Selection {
    pub blocks: Vec<Selected>,
    /// Tiles the selection read (to be protected from eviction).
    pub used: Vec<TileKey>,
    /// Held tiles it would prefetch (blocks within the bound but near it): kept.
    pub kept: Vec<TileKey>,
    /// Tiles wanted, with their priority (error / delta of the block that wants them).
    pub wanted: Vec<(TileKey, f32)>,
    /// Blocks drawn over the bound and the largest error / delta among them.
    pub over_bound: usize,
    pub worst_factor: f32,
    /// Blocks outside the view frustum.
    pub culled: usize,
    /// The top tile was held (else nothing is drawn and the frame is over the bound).
    pub complete: bool,
}

impl Selection {
    /// Is this frame within the bound (every block that should split did)?
    pub fn within_bound(&self) -> bool {
        self.complete && self.over_bound == 0
    }
}

/// Relative world box of block `(lod, bx, bz)` between raw heights `lo` and `hi`.
fn block_box(grid: &Grid, anchor: [i64; 2], lod: u32, bx: u32, bz: u32, lo: f32, hi: f32) -> (Vec3, Vec3) {
    let size = (BLOCK_QUADS << lod) as i64;
    let (x0, z0) = (i64::from(bx) * size - anchor[0], i64::from(bz) * size - anchor[1]);
    let x = |s: i64| (s as f64 * grid.spacing[0]) as f32;
    let z = |s: i64| (s as f64 * grid.spacing[1]) as f32;
    let y = |h: f32| (f64::from(h) * grid.height_scale) as f32;
    (Vec3::new(x(x0), y(lo), z(z0)), Vec3::new(x(x0 + size), y(hi), z(z0 + size)))
}

/// Selects the blocks of a frame from the tiles `cache` holds.
pub fn select(grid: &Grid, cache: &HostCache, view: &View, delta: f32, prefetch: f32) -> Selection {
    let mut out = Selection { worst_factor: 1.0, ..Default::default() };
    let root = root_lod(grid);
    let top = serving_tile(grid, root, 0, 0);
    if !cache.contains(top) {
        out.wanted.push((top, f32::INFINITY));
        return out;
    }
    out.complete = true;
    let (anchor, cam) = view.relative(grid);
    let frustum = cam.frustum();
    let (mut used, mut kept) = (std::collections::HashSet::new(), std::collections::HashSet::new());
    let mut stack = vec![(root, 0u32, 0u32)];
    while let Some((lod, bx, bz)) = stack.pop() {
        let size = BLOCK_QUADS << lod;
        if bx as usize * size >= grid.width - 1 || bz as usize * size >= grid.height - 1 {
            continue; // wholly outside the true extent
        }
        let key = serving_tile(grid, lod, bx, bz);
        let tile = cache.peek(key).expect("a block is visited only when its tile is held");
        used.insert(key);
        let s = tile.block(grid, lod, bx, bz);
        let (min, max) = block_box(grid, anchor, lod, bx, bz, s.lo - s.d, s.hi + s.d);
        if !frustum.intersects_aabb(min, max) {
            out.culled += 1;
            continue;
        }
        let error_px = (f64::from(s.d) * grid.height_scale) as f32 * world_to_pixels(&cam, min, max, delta);
        let finer = (lod > 0).then(|| serving_tile(grid, lod - 1, 2 * bx, 2 * bz));
        let finer_held = finer.is_some_and(|k| cache.contains(k));
        if error_px > delta && finer_held {
            for (cx, cz) in [(0, 0), (1, 0), (0, 1), (1, 1)] {
                stack.push((lod - 1, 2 * bx + cx, 2 * bz + cz));
            }
            continue;
        }
        let over = error_px > delta && lod > 0;
        if let Some(k) = finer.filter(|k| error_px > prefetch * delta && grid.stores(*k)) {
            if finer_held {
                kept.insert(k);
            } else {
                out.wanted.push((k, error_px / delta));
            }
        }
        if over {
            out.over_bound += 1;
            out.worst_factor = out.worst_factor.max(error_px / delta);
        }
        out.blocks.push(Selected { lod, bx, bz, tile: key, error_px, over });
    }
    out.used = used.into_iter().collect();
    out.used.sort();
    out.kept = kept.into_iter().collect();
    out.kept.sort();
    out
}
