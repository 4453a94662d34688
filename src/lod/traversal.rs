//! Quadtree traversal on the CPU (SPEC section 5, seed 000 section 3.3): which blocks to
//! draw, at which LOD, with their neighbours' LODs for crack-free stitching.

use crate::lod::block::{block_aabb, lod_map, map_in_pool, BlockLayout, DrawBlock, Traversal, EDGE_CORNERS};
use crate::lod::camera::{angular_factor, distance_to_aabb, world_to_pixels, Camera};
use crate::lod::gie::{BlockErrors, ErrorMode};
use crate::lod::heightfield::{Heightfield, RawSamples};
use crate::lod::morph;
use crate::lod::pyramid::MinMaxPyramid;
use foldhash::HashSet;

pub use crate::lod::morph::BlockCaches;
use glam::Vec3;

/// The distance rings' factor the renderers use for `--lod distance` (and before their
/// first error data): a block splits while the camera is nearer than twice its side.
pub const DISTANCE_FACTOR: f32 = 2.0;

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
    /// With `morph`, blocks geomorph from their parent's surface to their own, with the
    /// factors chosen inside the bound ([`crate::lod::morph`]).
    Errors { errors: &'a BlockErrors, computed_at: Vec3, delta: f32, mode: ErrorMode, stitch_bound: bool, morph: bool },
    /// Distance rings (the GeoMipMapping-style baseline): refine while the camera is
    /// closer than `factor` times the block's size.
    Distance { factor: f32 },
}

impl<'a> LodSelect<'a> {
    /// Error-driven selection as the renderer uses it: in strict mode the stitched
    /// strips are paid for in the bound; blocks morph.
    pub fn errors(errors: &'a BlockErrors, computed_at: Vec3, delta: f32, mode: ErrorMode) -> Self {
        LodSelect::Errors { errors, computed_at, delta, mode, stitch_bound: mode == ErrorMode::Strict, morph: true }
    }
    /// The same selection with morphing on or off.
    pub fn with_morph(self, on: bool) -> Self {
        match self {
            LodSelect::Errors { errors, computed_at, delta, mode, stitch_bound, .. } => {
                LodSelect::Errors { errors, computed_at, delta, mode, stitch_bound, morph: on }
            }
            other => other,
        }
    }
}
/// Traverses the quadtree top-down from the root (culling before splitting or drawing),
/// then chooses the blocks' morph factors when the selection morphs.
pub fn traverse(
    hf: &Heightfield,
    mm: &MinMaxPyramid,
    caches: &BlockCaches,
    layout: &BlockLayout,
    cam: &Camera,
    select: LodSelect,
) -> Traversal {
    let mut out = select_blocks(hf, mm, caches, layout, cam, select);
    if let LodSelect::Errors { delta, morph: true, .. } = select {
        morph::assign(hf, mm, caches, layout, cam, delta, &mut out);
    }
    out
}

/// The block selection. A block more than `m` LODs finer than a neighbour (`k = 2^m + 1`)
/// forces that neighbour to split, so that no block's corner lies inside a coarser
/// edge's segment (a T-junction); in strict mode with the stitch bound, so does a block
/// whose stitched strip along a coarser neighbour exceeds delta. The traversal is
/// repeated until neither happens (each block is forced at most once, so it ends).
fn select_blocks(
    hf: &Heightfield,
    mm: &MinMaxPyramid,
    caches: &BlockCaches,
    layout: &BlockLayout,
    cam: &Camera,
    select: LodSelect,
) -> Traversal {
    let mut forced = HashSet::default();
    loop {
        let mut out = traverse_once(hf, mm, layout, cam, select, &forced);
        out.stitch_splits = forced.len();
        let strict = match select {
            LodSelect::Errors { delta, mode: ErrorMode::Strict, stitch_bound: true, .. } => Some(delta),
            _ => None,
        };
        let before = forced.len();
        if strict.is_some() {
            // The strips of blocks seen for the first time are computed here, on every
            // core of the caller's pool, rather than one by one below.
            map_in_pool(&out.blocks, |_, b| {
                if b.coarser != [0; 4] {
                    caches.stitch.get(hf, layout, b);
                }
            });
        }
        let [cells, rows] = layout.cells().map(|c| c as i64);
        for b in &out.blocks {
            if b.coarser == [0; 4] {
                continue;
            }
            // The strips' error in pixels, in strict mode.
            let strip_px = strict.map(|delta| {
                let strips = caches.stitch.get(hf, layout, b);
                let (mut min, mut max) = block_aabb(hf, mm, layout, b.lod, b.bx, b.bz);
                min.y = min.y.min(strips.lo * hf.height_scale);
                max.y = max.y.max(strips.hi * hf.height_scale);
                strips.edge.map(|d| d * hf.height_scale * world_to_pixels(cam, min, max, delta))
            });
            for (e, (nx, nz)) in b.cells_across().into_iter().enumerate() {
                if b.coarser[e] == 0 {
                    continue;
                }
                // More than m levels apart, this block's corner lies inside a segment of
                // the coarser edge: a T-junction, which rasterizes with pinholes.
                let t_junction = b.coarser[e] > b.stride() << layout.m;
                let over = match (strict, strip_px) {
                    (Some(delta), Some(px)) if px[e] <= delta => {
                        out.max_block_error = out.max_block_error.max(px[e]);
                        false
                    }
                    (Some(_), Some(_)) => true,
                    _ => false,
                };
                if !(t_junction || over) {
                    continue;
                }
                if nx >= 0 && nz >= 0 && nx < cells && nz < rows {
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
    // Blocks still to visit, with their parent's selection error.
    // Every root, the last first (the stack pops in reverse).
    let [rx, rz] = layout.roots.map(|r| r as u32);
    let mut stack: Vec<(u32, u32, u32, f32)> =
        (0..rz).flat_map(|bz| (0..rx).map(move |bx| (layout.root_lod(), bx, bz, f32::INFINITY))).rev().collect();
    while let Some((lod, bx, bz, parent_err)) = stack.pop() {
        let (ox, oz) = (bx * layout.block_samples(lod), bz * layout.block_samples(lod));
        if ox as usize >= hf.width - 1 || oz as usize >= hf.height - 1 {
            continue; // wholly in the embedding margin
        }
        let (min, max) = block_aabb(hf, mm, layout, lod, bx, bz);
        if !frustum.intersects_aabb(min, max) {
            out.frustum_culled.push(DrawBlock::new(lod, bx, bz));
            continue;
        }
        let mut stale_split = false;
        let (draw, err) = if lod == 0 {
            (true, 0.0)
        } else if forced.contains(&(lod, bx, bz)) {
            (false, 0.0)
        } else {
            match select {
                LodSelect::Full => (false, 0.0),
                LodSelect::Errors { errors, computed_at, delta, mode, .. } => {
                    let data = errors.get(lod, bx as usize, bz as usize);
                    let mut e = stale_corrected(data, computed_at, cam.position, min, max);
                    let mut fresh =
                        data * distance_to_aabb(computed_at, min, max) / distance_to_aabb(cam.position, min, max);
                    if mode == ErrorMode::Strict {
                        // The GPU data holds D * kappa / distance; the angles are this frame's.
                        let angles = angular_factor(cam, min, max, delta);
                        e *= angles;
                        fresh *= angles;
                    }
                    stale_split = e > delta && fresh <= delta;
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
            out.blocks.push(DrawBlock::new(lod, bx, bz));
            out.selection_errors.push([err, parent_err]);
        } else {
            out.stale_splits += stale_split as usize;
            for (cx, cz) in [(1, 1), (0, 1), (1, 0), (0, 0)] {
                stack.push((lod - 1, bx * 2 + cx, bz * 2 + cz, err));
            }
        }
    }
    // Front to back, so that the depth test rejects hidden terrain before it is shaded.
    let distance = |b: &DrawBlock| {
        let (min, max) = block_aabb(hf, mm, layout, b.lod, b.bx, b.bz);
        distance_to_aabb(cam.position, min, max)
    };
    let mut order: Vec<(f32, DrawBlock, [f32; 2])> =
        out.blocks.iter().zip(&out.selection_errors).map(|(b, e)| (distance(b), *b, *e)).collect();
    order.sort_by(|a, b| a.0.total_cmp(&b.0));
    out.blocks = order.iter().map(|o| o.1).collect();
    out.selection_errors = order.iter().map(|o| o.2).collect();
    out.nearest = order.first().map(|o| o.0);
    out.lod_map = stitch_selection(hf, layout, &mut out.blocks);
    out
}

/// Gives a selection's blocks their coarser neighbours' strides and resolved corners
/// (what the vertex shader stitches with), and returns its LOD map. One copy for the
/// in-memory traversal and streamed frames.
pub fn stitch_selection<S: RawSamples + ?Sized>(hf: &S, layout: &BlockLayout, blocks: &mut [DrawBlock]) -> Vec<i8> {
    let map = lod_map(layout, blocks);
    let [cells, rows] = layout.cells().map(|c| c as i64);
    stitch_blocks(hf, layout, blocks, &DenseLods { map: &map, cells, rows });
    map
}

/// The LOD of the selected block over finest-grid cell `(x, z)`, or -1 (outside, or no
/// block): a dense map over the terrain (in memory), or a lookup in the selection
/// (streamed terrains, whose dense map could take gigabytes: SPEC section 8).
pub trait LodAt {
    /// `near`: a LOD the answer is likely close to (the asking block's): where to look
    /// first.
    fn lod_at(&self, x: i64, z: i64, near: u32) -> i8;
}

/// The dense map of [`lod_map`].
pub struct DenseLods<'a> {
    pub map: &'a [i8],
    pub cells: i64,
    pub rows: i64,
}

impl LodAt for DenseLods<'_> {
    fn lod_at(&self, x: i64, z: i64, _near: u32) -> i8 {
        if x < 0 || z < 0 || x >= self.cells || z >= self.rows {
            -1
        } else {
            self.map[(z * self.cells + x) as usize]
        }
    }
}

/// The selection's blocks by position, looked up level by level outward from `near`.
pub struct SparseLods {
    blocks: foldhash::HashSet<(u32, u32, u32)>,
    top: u32,
    cells: i64,
    rows: i64,
}

impl SparseLods {
    pub fn new(layout: &BlockLayout, blocks: &[DrawBlock]) -> Self {
        let [cells, rows] = layout.cells().map(|c| c as i64);
        SparseLods { blocks: blocks.iter().map(|b| (b.lod, b.bx, b.bz)).collect(), top: layout.root_lod(), cells, rows }
    }
}

impl LodAt for SparseLods {
    fn lod_at(&self, x: i64, z: i64, near: u32) -> i8 {
        if x < 0 || z < 0 || x >= self.cells || z >= self.rows {
            return -1;
        }
        let held = |l: u32| self.blocks.contains(&(l, (x >> l) as u32, (z >> l) as u32));
        let near = near.min(self.top);
        for d in 0..=self.top {
            if held(near + d) && near + d <= self.top {
                return (near + d) as i8;
            }
            if d <= near && d > 0 && held(near - d) {
                return (near - d) as i8;
            }
        }
        -1
    }
}

/// Gives `blocks` their coarser neighbours' strides and resolved corners from `lods`.
pub fn stitch_blocks<S: RawSamples + ?Sized, L: LodAt>(
    hf: &S,
    layout: &BlockLayout,
    blocks: &mut [DrawBlock],
    lods: &L,
) {
    assign_neighbours(blocks, lods);
    resolve_corners(hf, layout, blocks, lods);
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
fn assign_neighbours<L: LodAt>(blocks: &mut [DrawBlock], lods: &L) {
    for b in blocks.iter_mut() {
        let span = 1i64 << b.lod;
        let (cx, cz) = (b.bx as i64 * span, b.bz as i64 * span);
        let at = |x: i64, z: i64| lods.lod_at(x, z, b.lod);
        let across = [at(cx, cz - 1), at(cx + span, cz), at(cx, cz + span), at(cx - 1, cz)];
        for (i, l) in across.iter().enumerate() {
            b.coarser[i] = if *l > b.lod as i8 { 1u32 << *l } else { 0 };
        }
    }
}

/// Sets every block's corner heights. A corner strictly inside a coarser neighbour's edge
/// lies on that edge's line between its vertices; those are raw samples, or that
/// neighbour's own corners, resolved before (coarsest first).
pub fn resolve_corners<S: RawSamples + ?Sized, L: LodAt>(
    hf: &S,
    layout: &BlockLayout,
    blocks: &mut [DrawBlock],
    lods: &L,
) {
    let index: foldhash::HashMap<(u32, u32, u32), usize> =
        blocks.iter().enumerate().map(|(i, b)| ((b.lod, b.bx, b.bz), i)).collect();
    let mut order: Vec<usize> = (0..blocks.len()).collect();
    order.sort_by_key(|&i| std::cmp::Reverse(blocks[i].lod));
    let last = layout.k() - 1;
    for i in order {
        let b = blocks[i];
        let across = b.cells_across();
        let stride = b.stride() as i64;
        let (ox, oz) = b.origin(layout);
        for (c, (u, v)) in [(0, 0), (last, 0), (last, last), (0, last)].into_iter().enumerate() {
            let (sx, sz) = (ox as i64 + u as i64 * stride, oz as i64 + v as i64 * stride);
            let mut h = hf.raw_at(sx, sz);
            for (s, corners) in EDGE_CORNERS.iter().enumerate() {
                let ns = b.coarser[s] as i64;
                if ns == 0 || !corners.contains(&c) {
                    continue;
                }
                let (nx, nz) = across[s];
                let l = lods.lod_at(nx, nz, b.lod) as u32;
                let Some(&x) = index.get(&(l, (nx >> l) as u32, (nz >> l) as u32)) else { continue };
                let xb = blocks[x];
                let size = layout.block_samples(l) as i64;
                let (xo, zo) = xb.origin(layout);
                let (coord, start) = if s % 2 == 0 { (sx, xo as i64) } else { (sz, zo as i64) };
                if coord % size == 0 {
                    continue; // also a corner of the neighbour's
                }
                // The neighbour's edge facing this block, and its vertex heights.
                let facing = (s + 2) % 4;
                let vertex = |at: i64| -> f32 {
                    let (px, pz) = if s % 2 == 0 { (at, sz) } else { (sx, at) };
                    if at == start {
                        xb.corner(EDGE_CORNERS[facing][0], hf, px, pz)
                    } else if at == start + size {
                        xb.corner(EDGE_CORNERS[facing][1], hf, px, pz)
                    } else {
                        hf.raw_at(px, pz)
                    }
                };
                let r = coord % ns;
                h = if r == 0 {
                    vertex(coord)
                } else {
                    let (ha, hb) = (vertex(coord - r), vertex(coord - r + ns));
                    ha + (hb - ha) * (r as f32 / ns as f32)
                };
            }
            blocks[i].corner_raw[c] = h.to_bits();
        }
    }
}
