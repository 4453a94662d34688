//! Quadtree traversal on the CPU (SPEC section 5, seed 000 section 3.3): which blocks to
//! draw, at which LOD, with their neighbours' LODs for crack-free stitching.

use crate::camera::{distance_to_aabb, Camera, Frustum};
use crate::gie::{BlockErrors, ErrorMode};
use crate::heightfield::{Heightfield, MinMaxPyramid};
use glam::Vec3;
use std::collections::HashSet;

/// Block geometry: `k = 2^m + 1` vertices a side; a block of LOD `j` covers `2^(m+j)`
/// samples; the root is at LOD `n - m`.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct BlockLayout {
    pub n: u32,
    pub m: u32,
}

impl BlockLayout {
    /// `k` must be `2^m + 1` with `m >= 1`; a block larger than the terrain is shrunk to
    /// the terrain.
    pub fn new(n: u32, k: u32) -> Result<Self, String> {
        if k < 3 || !(k - 1).is_power_of_two() {
            return Err(format!("--block {k}: the block side must be 2^m + 1 (3, 5, 9, 17, 33, 65, ...)"));
        }
        if k > 257 {
            return Err(format!("--block {k}: at most 257 (vertex coordinates are 8-bit)"));
        }
        let m = (k - 1).trailing_zeros().min(n);
        Ok(BlockLayout { n, m })
    }
    pub fn k(&self) -> u32 {
        (1 << self.m) + 1
    }
    pub fn root_lod(&self) -> u32 {
        self.n - self.m
    }
    /// Samples a block of this LOD covers, edge to edge.
    pub fn block_samples(&self, lod: u32) -> u32 {
        1 << (self.m + lod)
    }
    /// Cells of the finest block grid a side (`2^(n-m)`).
    pub fn cells(&self) -> usize {
        1 << self.root_lod()
    }
    /// Triangles in one block.
    pub fn triangles_per_block(&self) -> u64 {
        let q = (self.k() - 1) as u64;
        2 * q * q
    }
}

/// A block to draw: LOD, block coordinates at that LOD, and the stride of each coarser
/// neighbour (0 when the neighbour is not coarser): north (-z), east (+x), south (+z),
/// west (-x).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct DrawBlock {
    pub lod: u32,
    pub bx: u32,
    pub bz: u32,
    pub coarser: [u32; 4],
}

impl DrawBlock {
    pub fn origin(&self, layout: &BlockLayout) -> (u32, u32) {
        let s = layout.block_samples(self.lod);
        (self.bx * s, self.bz * s)
    }
    pub fn stride(&self) -> u32 {
        1 << self.lod
    }
}

/// How the LOD of each block is chosen.
#[derive(Clone, Copy, Debug)]
pub enum LodSelect<'a> {
    /// Every visible block at LOD 0 (the brute-force reference).
    Full,
    /// The paper's method: refine while the block error exceeds `delta` pixels. `errors`
    /// were computed for a camera at `computed_at`. In strict mode the traversal also
    /// applies each block's own `1 / cos^2` and, with `stitch_bound`, the deviation of
    /// its stitched strips (splitting coarser neighbours until they fit): see
    /// [`LodSelect::errors`].
    Errors { errors: &'a BlockErrors, computed_at: Vec3, delta: f32, mode: ErrorMode, stitch_bound: bool },
    /// Distance rings (the GeoMipMapping-style baseline): refine while the camera is
    /// closer than `factor` times the block's size.
    Distance { factor: f32 },
}

impl<'a> LodSelect<'a> {
    /// Error-driven selection as the renderer uses it: in strict mode the stitched
    /// strips are paid for in the bound.
    pub fn errors(errors: &'a BlockErrors, computed_at: Vec3, delta: f32, mode: ErrorMode) -> Self {
        LodSelect::Errors { errors, computed_at, delta, mode, stitch_bound: mode == ErrorMode::Strict }
    }
}

#[derive(Clone, Debug, Default)]
pub struct Traversal {
    pub blocks: Vec<DrawBlock>,
    /// Largest error (pixels) the traversal accepted for a drawn block: stale-corrected,
    /// with the block's off-axis factor and stitched strips in strict mode.
    pub max_block_error: f32,
    /// LOD of the drawn block over each finest-grid cell, -1 where nothing is drawn.
    pub lod_map: Vec<i8>,
    /// Blocks split only because a finer neighbour's stitched strip exceeded delta.
    pub stitch_splits: usize,
    /// Distance from the camera to the nearest drawn block's box.
    pub nearest: Option<f32>,
}

/// World-space AABB of a block.
pub fn block_aabb(
    hf: &Heightfield,
    mm: &MinMaxPyramid,
    layout: &BlockLayout,
    lod: u32,
    bx: u32,
    bz: u32,
) -> (Vec3, Vec3) {
    let level = layout.m + lod;
    let s = layout.block_samples(lod) as f32 * hf.spacing;
    let [lo, hi] = mm.get(level, bx as usize, bz as usize);
    (
        Vec3::new(bx as f32 * s, lo * hf.height_scale, bz as f32 * s),
        Vec3::new((bx + 1) as f32 * s, hi * hf.height_scale, (bz + 1) as f32 * s),
    )
}

/// Traverses the quadtree top-down from the root (culling before splitting or drawing).
/// In strict mode with the stitch bound, a block whose stitched strip along a coarser
/// neighbour exceeds delta forces that neighbour to split; the traversal is repeated
/// until no strip exceeds delta (each block is forced at most once, so it ends).
pub fn traverse(
    hf: &Heightfield,
    mm: &MinMaxPyramid,
    layout: &BlockLayout,
    cam: &Camera,
    select: LodSelect,
) -> Traversal {
    let mut forced = HashSet::new();
    loop {
        let mut out = traverse_once(hf, mm, layout, cam, select, &forced);
        out.stitch_splits = forced.len();
        let delta = match select {
            LodSelect::Errors { delta, mode: ErrorMode::Strict, stitch_bound: true, .. } => delta,
            _ => return out,
        };
        let before = forced.len();
        let cells = layout.cells() as i64;
        for b in &out.blocks {
            if b.coarser == [0; 4] {
                continue;
            }
            let strips = mm.stitch.get(hf, layout, b);
            let (mut min, mut max) = block_aabb(hf, mm, layout, b.lod, b.bx, b.bz);
            min.y = min.y.min(strips.lo * hf.height_scale);
            max.y = max.y.max(strips.hi * hf.height_scale);
            let px_per_world = world_to_pixels(cam, min, max, delta);
            let span = 1i64 << b.lod;
            let (cx, cz) = (b.bx as i64 * span, b.bz as i64 * span);
            for (e, (nx, nz)) in [(cx, cz - 1), (cx + span, cz), (cx, cz + span), (cx - 1, cz)].into_iter().enumerate()
            {
                if b.coarser[e] == 0 {
                    continue;
                }
                let err = strips.edge[e] * hf.height_scale * px_per_world;
                if err <= delta {
                    out.max_block_error = out.max_block_error.max(err);
                    continue;
                }
                if nx >= 0 && nz >= 0 && nx < cells && nz < cells {
                    let lod = out.lod_map[(nz * cells + nx) as usize];
                    if lod > 0 {
                        forced.insert((lod as u32, (nx >> lod) as u32, (nz >> lod) as u32));
                    }
                }
            }
        }
        if forced.len() == before {
            return out;
        }
    }
}

/// Pixels per world unit of a vertical deviation inside the box `[min, max]` for this
/// camera: `kappa cos(beta_b) / (cos^2(theta_b) * distance)`, see [`angular_factor`];
/// valid for deviations that are then checked against `delta` pixels.
pub fn world_to_pixels(cam: &Camera, min: Vec3, max: Vec3, delta: f32) -> f32 {
    cam.kappa() * angular_factor(cam, min, max, delta) / distance_to_aabb(cam.position, min, max).max(cam.near)
}

/// What the camera's orientation does to a vertical deviation inside the box, on top of
/// `kappa / distance` (the GPU data): the projection magnifies by up to
/// `1 / cos^2(theta_b)` off the optical axis, and only the part of a vertical segment
/// across the ray shows, at most `cos(beta_b)` of it (SPEC section 3). The off-axis
/// angle is clamped to the frustum widened by `delta` pixels, which is sound for an error
/// then compared with `delta` ([`Camera::inv_cos2_aabb`]).
pub fn angular_factor(cam: &Camera, min: Vec3, max: Vec3, delta: f32) -> f32 {
    cam.inv_cos2_aabb(min, max, delta) * cam.vertical_factor_aabb(min, max)
}

fn traverse_once(
    hf: &Heightfield,
    mm: &MinMaxPyramid,
    layout: &BlockLayout,
    cam: &Camera,
    select: LodSelect,
    forced: &HashSet<(u32, u32, u32)>,
) -> Traversal {
    let frustum = cam.frustum();
    let mut out = Traversal::default();
    let mut stack = vec![(layout.root_lod(), 0u32, 0u32)];
    while let Some((lod, bx, bz)) = stack.pop() {
        let (ox, oz) = (bx * layout.block_samples(lod), bz * layout.block_samples(lod));
        if ox as usize >= hf.width - 1 || oz as usize >= hf.height - 1 {
            continue; // wholly in the embedding margin
        }
        let (min, max) = block_aabb(hf, mm, layout, lod, bx, bz);
        if !frustum.intersects_aabb(min, max) {
            continue;
        }
        let (draw, err) = if lod == 0 {
            (true, 0.0)
        } else if forced.contains(&(lod, bx, bz)) {
            (false, 0.0)
        } else {
            match select {
                LodSelect::Full => (false, 0.0),
                LodSelect::Errors { errors, computed_at, delta, mode, .. } => {
                    let mut e =
                        stale_corrected(errors.get(lod, bx as usize, bz as usize), computed_at, cam.position, min, max);
                    if mode == ErrorMode::Strict {
                        // The GPU data holds D * kappa / distance; the angles are this frame's.
                        e *= angular_factor(cam, min, max, delta);
                    }
                    (e <= delta, e)
                }
                LodSelect::Distance { factor } => {
                    let d = distance_to_aabb(cam.position, min, max);
                    (d > factor * (max.x - min.x), 0.0)
                }
            }
        };
        if draw {
            out.max_block_error = out.max_block_error.max(err);
            out.blocks.push(DrawBlock { lod, bx, bz, coarser: [0; 4] });
        } else {
            for (cx, cz) in [(1, 1), (0, 1), (1, 0), (0, 0)] {
                stack.push((lod - 1, bx * 2 + cx, bz * 2 + cz));
            }
        }
    }
    // Front to back, so that the depth test rejects hidden terrain before it is shaded.
    let distance = |b: &DrawBlock| {
        let (min, max) = block_aabb(hf, mm, layout, b.lod, b.bx, b.bz);
        distance_to_aabb(cam.position, min, max)
    };
    out.blocks.sort_by_cached_key(|b| distance(b).to_bits());
    out.nearest = out.blocks.first().map(distance);
    out.lod_map = lod_map(layout, &out.blocks);
    assign_neighbours(layout, &mut out.blocks, &out.lod_map);
    out
}

/// Error data computed at `old` used at `now` (SPEC section 5): the error scales like
/// `1/d`, and the block is at least `d - m` away now.
pub fn stale_corrected(err: f32, old: Vec3, now: Vec3, min: Vec3, max: Vec3) -> f32 {
    let moved = (now - old).length();
    if moved == 0.0 || err == 0.0 {
        return err;
    }
    let d = distance_to_aabb(old, min, max);
    if d <= moved {
        f32::INFINITY
    } else {
        err * d / (d - moved)
    }
}

/// LOD of the drawn block over each finest-grid cell (-1: nothing drawn there).
pub fn lod_map(layout: &BlockLayout, blocks: &[DrawBlock]) -> Vec<i8> {
    let cells = layout.cells();
    let mut map = vec![-1i8; cells * cells];
    for b in blocks {
        let span = 1usize << b.lod;
        let (cx, cz) = (b.bx as usize * span, b.bz as usize * span);
        for z in cz..cz + span {
            map[z * cells + cx..z * cells + cx + span].fill(b.lod as i8);
        }
    }
    map
}

fn assign_neighbours(layout: &BlockLayout, blocks: &mut [DrawBlock], map: &[i8]) {
    let cells = layout.cells() as i64;
    let at = |x: i64, z: i64| -> i8 {
        if x < 0 || z < 0 || x >= cells || z >= cells {
            -1
        } else {
            map[(z * cells + x) as usize]
        }
    };
    for b in blocks.iter_mut() {
        let span = 1i64 << b.lod;
        let (cx, cz) = (b.bx as i64 * span, b.bz as i64 * span);
        let across = [at(cx, cz - 1), at(cx + span, cz), at(cx, cz + span), at(cx - 1, cz)];
        for (i, l) in across.iter().enumerate() {
            b.coarser[i] = if *l > b.lod as i8 { 1u32 << *l } else { 0 };
        }
    }
}

/// The vertex shader's placement of block vertex `(u, v)`, in plain Rust: the sample it
/// lands on and its raw height (SPEC section 5, cracks). Must match `glsl/terrain.vert`.
pub fn block_vertex(hf: &Heightfield, layout: &BlockLayout, b: &DrawBlock, u: u32, v: u32) -> (i64, i64, f32) {
    let k = layout.k();
    let stride = b.stride() as i64;
    let (ox, oz) = b.origin(layout);
    let (mut sx, mut sz) = (ox as i64 + u as i64 * stride, oz as i64 + v as i64 * stride);
    let cn = b.coarser;
    let (mut best, mut axis) = (0i64, 0);
    if v == 0 && cn[0] as i64 > best {
        best = cn[0] as i64;
        axis = 0;
    }
    if v == k - 1 && cn[2] as i64 > best {
        best = cn[2] as i64;
        axis = 0;
    }
    if u == k - 1 && cn[1] as i64 > best {
        best = cn[1] as i64;
        axis = 1;
    }
    if u == 0 && cn[3] as i64 > best {
        best = cn[3] as i64;
        axis = 1;
    }
    let coord = if axis == 0 { sx } else { sz };
    let rem = if best > 0 { coord % best } else { 0 };
    if rem == 0 {
        (sx, sz, hf.raw_at(sx, sz))
    } else if best <= (k as i64 - 1) * stride {
        if axis == 0 {
            sx -= rem;
        } else {
            sz -= rem;
        }
        (sx, sz, hf.raw_at(sx, sz))
    } else {
        let (mut ax, mut az, mut bx, mut bz) = (sx, sz, sx, sz);
        if axis == 0 {
            ax -= rem;
            bx = ax + best;
        } else {
            az -= rem;
            bz = az + best;
        }
        let ra = hf.raw_at(ax, az);
        let rb = hf.raw_at(bx, bz);
        (sx, sz, ra + (rb - ra) * (rem as f32 / best as f32))
    }
}

/// Frustum-visible test for the finest cell `(cx, cz)` (used by the tiling check).
pub fn cell_visible(
    hf: &Heightfield,
    mm: &MinMaxPyramid,
    layout: &BlockLayout,
    frustum: &Frustum,
    cx: u32,
    cz: u32,
) -> bool {
    let s = layout.block_samples(0);
    if (cx * s) as usize >= hf.width - 1 || (cz * s) as usize >= hf.height - 1 {
        return false;
    }
    let (min, max) = block_aabb(hf, mm, layout, 0, cx, cz);
    frustum.intersects_aabb(min, max)
}
