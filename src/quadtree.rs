//! Quadtree traversal on the CPU (SPEC section 5, seed 000 section 3.3): which blocks to
//! draw, at which LOD, with their neighbours' LODs for crack-free stitching.

use crate::camera::{distance_to_aabb, Camera, Frustum};
use crate::gie::{BlockErrors, ErrorMode};
use crate::heightfield::{Heightfield, MinMaxPyramid};
use foldhash::HashSet;
use glam::Vec3;

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

/// Morph factors are multiples of `1 / MORPH_ONE`, exact in f32 on the CPU and the GPU.
pub const MORPH_ONE: u16 = 1024;

/// A morph factor as the shaders get it.
pub fn morph_value(q: u16) -> f32 {
    q as f32 / MORPH_ONE as f32
}

/// A block to draw: LOD, block coordinates at that LOD, the stride of each coarser
/// neighbour (0 when the neighbour is not coarser): north (-z), east (+x), south (+z),
/// west (-x), and its geomorph (see [`crate::morph`]).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub struct DrawBlock {
    pub lod: u32,
    pub bx: u32,
    pub bz: u32,
    pub coarser: [u32; 4],
    /// Morph factor of the interior vertices: 0 puts the block's odd vertices on its
    /// parent's surface, [`MORPH_ONE`] on its own samples.
    pub morph: u16,
    /// Morph factor of the vertices on each edge; on an edge next to a coarser block, of
    /// that block's vertices there, which this block's edge follows.
    pub edge_morph: [u16; 4],
    /// Raw height of each corner (NW, NE, SE, SW) as f32 bits, or [`CORNER_UNRESOLVED`]:
    /// a corner inside a coarser neighbour's edge lies on that edge, whose own corners
    /// may lie on a coarser one's, so the traversal resolves them ([`resolve_corners`]).
    pub corner_raw: [u32; 4],
}

/// A corner whose height is its sample's (blocks made outside the traversal).
pub const CORNER_UNRESOLVED: u32 = u32::MAX;

/// The corners at the start and the end of each edge (north, east, south, west), in the
/// direction of increasing x or z.
const EDGE_CORNERS: [[usize; 2]; 4] = [[0, 1], [1, 2], [3, 2], [0, 3]];

impl DrawBlock {
    /// An unmorphed block with no coarser neighbour.
    pub fn new(lod: u32, bx: u32, bz: u32) -> Self {
        DrawBlock {
            lod,
            bx,
            bz,
            coarser: [0; 4],
            morph: MORPH_ONE,
            edge_morph: [MORPH_ONE; 4],
            corner_raw: [CORNER_UNRESOLVED; 4],
        }
    }
    /// Raw height of corner `c` at sample `(x, z)`.
    pub fn corner(&self, c: usize, hf: &Heightfield, x: i64, z: i64) -> f32 {
        match self.corner_raw[c] {
            CORNER_UNRESOLVED => hf.raw_at(x, z),
            bits => f32::from_bits(bits),
        }
    }
    /// The block with every vertex at its own LOD (factor 1): the surface the selection
    /// bounds.
    pub fn unmorphed(&self) -> Self {
        DrawBlock { morph: MORPH_ONE, edge_morph: [MORPH_ONE; 4], ..*self }
    }
    pub fn origin(&self, layout: &BlockLayout) -> (u32, u32) {
        let s = layout.block_samples(self.lod);
        (self.bx * s, self.bz * s)
    }
    pub fn stride(&self) -> u32 {
        1 << self.lod
    }
    /// The finest-grid cell just across each edge (north, east, south, west) from the
    /// edge's first cell; it may lie outside the grid.
    pub fn cells_across(&self) -> [(i64, i64); 4] {
        let span = 1i64 << self.lod;
        let (cx, cz) = (self.bx as i64 * span, self.bz as i64 * span);
        [(cx, cz - 1), (cx + span, cz), (cx, cz + span), (cx - 1, cz)]
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
    /// With `morph`, blocks geomorph from their parent's surface to their own, with the
    /// factors chosen inside the bound ([`crate::morph`]).
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

#[derive(Clone, Debug, Default)]
pub struct Traversal {
    pub blocks: Vec<DrawBlock>,
    /// Largest error (pixels) the traversal accepted for a drawn block: stale-corrected,
    /// with the block's off-axis factor and stitched strips in strict mode.
    pub max_block_error: f32,
    /// LOD of the drawn block over each finest-grid cell, -1 where nothing is drawn.
    pub lod_map: Vec<i8>,
    /// Blocks split only because a finer neighbour's stitched strip exceeded delta or the
    /// neighbour was more than `m` LODs finer.
    pub stitch_splits: usize,
    /// Distance from the camera to the nearest drawn block's box.
    pub nearest: Option<f32>,
    /// Blocks drawn part way between their parent's surface and their own.
    pub morphing: usize,
    /// Blocks split only because their error data is stale: the stale-corrected error
    /// exceeds delta, but the data scaled to this camera's distance (`1 / d`, the
    /// estimate of what a new generation would hold) does not. New data can pay only
    /// when this is above zero (the refresh policy).
    pub stale_splits: usize,
    /// Per drawn block: the error the selection accepted for it and the one for which it
    /// split its parent (pixels; 0 where not error-driven, infinite for the root).
    pub selection_errors: Vec<[f32; 2]>,
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

/// Traverses the quadtree top-down from the root (culling before splitting or drawing),
/// then chooses the blocks' morph factors when the selection morphs.
pub fn traverse(
    hf: &Heightfield,
    mm: &MinMaxPyramid,
    layout: &BlockLayout,
    cam: &Camera,
    select: LodSelect,
) -> Traversal {
    let mut out = select_blocks(hf, mm, layout, cam, select);
    if let LodSelect::Errors { delta, morph: true, .. } = select {
        crate::morph::assign(hf, mm, layout, cam, delta, &mut out);
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
        let cells = layout.cells() as i64;
        for b in &out.blocks {
            if b.coarser == [0; 4] {
                continue;
            }
            // The strips' error in pixels, in strict mode.
            let strip_px = strict.map(|delta| {
                let strips = mm.stitch.get(hf, layout, b);
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
    // Blocks still to visit, with their parent's selection error.
    let mut stack = vec![(layout.root_lod(), 0u32, 0u32, f32::INFINITY)];
    while let Some((lod, bx, bz, parent_err)) = stack.pop() {
        let (ox, oz) = (bx * layout.block_samples(lod), bz * layout.block_samples(lod));
        if ox as usize >= hf.width - 1 || oz as usize >= hf.height - 1 {
            continue; // wholly in the embedding margin
        }
        let (min, max) = block_aabb(hf, mm, layout, lod, bx, bz);
        if !frustum.intersects_aabb(min, max) {
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
    out.lod_map = lod_map(layout, &out.blocks);
    assign_neighbours(layout, &mut out.blocks, &out.lod_map);
    resolve_corners(hf, layout, &mut out.blocks, &out.lod_map);
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

/// Sets every block's corner heights. A corner strictly inside a coarser neighbour's edge
/// lies on that edge's line between its vertices; those are raw samples, or that
/// neighbour's own corners, resolved before (coarsest first).
pub fn resolve_corners(hf: &Heightfield, layout: &BlockLayout, blocks: &mut [DrawBlock], map: &[i8]) {
    let cells = layout.cells() as i64;
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
                let l = map[(nz * cells + nx) as usize] as u32;
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

/// The vertex shader's placement of block vertex `(u, v)`, in plain Rust: the sample it
/// lands on and its raw height, stitched and morphed (SPEC section 5). Must match
/// `glsl/block_vertex.glsl` bit for bit.
pub fn block_vertex(hf: &Heightfield, layout: &BlockLayout, b: &DrawBlock, u: u32, v: u32) -> (i64, i64, f32) {
    let last = layout.k() - 1;
    let stride = b.stride() as i64;
    let (ox, oz) = b.origin(layout);
    let (mut sx, mut sz) = (ox as i64 + u as i64 * stride, oz as i64 + v as i64 * stride);
    if let Some(c) = [(0, 0), (last, 0), (last, last), (0, last)].iter().position(|&p| p == (u, v)) {
        return (sx, sz, b.corner(c, hf, sx, sz));
    }
    // Other edge vertices next to a coarser block follow that block's edge.
    let side =
        [(0, v == 0), (2, v == last), (1, u == last), (3, u == 0)].into_iter().find(|&(s, on)| on && b.coarser[s] > 0);
    let Some((side, _)) = side else {
        return (sx, sz, own_vertex_raw(hf, b, last, u, v, sx, sz));
    };
    let best = b.coarser[side] as i64;
    let along = if side % 2 == 0 { u } else { v };
    let coord = if side % 2 == 0 { sx } else { sz };
    let rem = coord % best;
    let [first, second] = EDGE_CORNERS[side];
    if rem == 0 {
        // A vertex of the coarser block, inside its edge.
        (sx, sz, coarse_vertex_raw(hf, b, side, sx, sz))
    } else if best <= last as i64 * stride {
        // The neighbour has vertices at both ends of this edge: collapse onto the one
        // below (degenerate triangles, no T-junction).
        if side % 2 == 0 {
            sx -= rem;
        } else {
            sz -= rem;
        }
        let h = if along as i64 * stride == rem {
            b.corner(first, hf, sx, sz)
        } else {
            coarse_vertex_raw(hf, b, side, sx, sz)
        };
        (sx, sz, h)
    } else {
        // The whole edge lies inside one segment of the neighbour (LODs more than m
        // apart: never in the traversal's block lists, which split such neighbours, but
        // a block list may come from elsewhere): on the line between this edge's
        // corners, which lie on that segment.
        let (ca, cb) = if side % 2 == 0 {
            (b.corner(first, hf, ox as i64, sz), b.corner(second, hf, ox as i64 + last as i64 * stride, sz))
        } else {
            (b.corner(first, hf, sx, oz as i64), b.corner(second, hf, sx, oz as i64 + last as i64 * stride))
        };
        (sx, sz, ca + (cb - ca) * (along as f32 / last as f32))
    }
}

/// Height of the coarser neighbour's vertex at `(sx, sz)` on the edge across `side`, as
/// that block draws it: its odd vertices morph with the edge's factor, which both blocks
/// are given ([`crate::morph`]), between the mean of the two vertices around it along
/// the edge and their own sample. The neighbour's origin is a multiple of twice its
/// stride, so a vertex's parity is that of its coordinate over the stride.
fn coarse_vertex_raw(hf: &Heightfield, b: &DrawBlock, side: usize, sx: i64, sz: i64) -> f32 {
    let raw = hf.raw_at(sx, sz);
    let best = b.coarser[side] as i64;
    let along_x = side.is_multiple_of(2);
    let coord = if along_x { sx } else { sz };
    let f = morph_value(b.edge_morph[side]);
    if (coord / best) % 2 == 0 || f >= 1.0 {
        return raw;
    }
    let (dx, dz) = if along_x { (best, 0) } else { (0, best) };
    let p = (hf.raw_at(sx - dx, sz - dz) + hf.raw_at(sx + dx, sz + dz)) * 0.5;
    morph_raw(p, raw, f)
}

/// `raw` moved towards the parent surface's height `p`: factor 1 is `raw` itself.
#[inline]
pub fn morph_raw(p: f32, raw: f32, f: f32) -> f32 {
    if f >= 1.0 {
        raw
    } else {
        p + (raw - p) * f
    }
}

/// Height of the block's own vertex `(u, v)` at sample `(sx, sz)`: a vertex at an odd
/// position lies on an edge or the a-i diagonal of its parent's quad, where the parent
/// surface is the mean of the two samples around it.
fn own_vertex_raw(hf: &Heightfield, b: &DrawBlock, last: u32, u: u32, v: u32, sx: i64, sz: i64) -> f32 {
    let raw = hf.raw_at(sx, sz);
    let (odd_u, odd_v) = (u % 2 == 1, v % 2 == 1);
    let q = match (v, u) {
        (0, _) => b.edge_morph[0],
        (_, _) if v == last => b.edge_morph[2],
        (_, _) if u == last => b.edge_morph[1],
        (_, 0) => b.edge_morph[3],
        _ => b.morph,
    };
    let f = morph_value(q);
    if !(odd_u || odd_v) || f >= 1.0 {
        return raw;
    }
    let s = b.stride() as i64;
    let (dx, dz) = (if odd_u { s } else { 0 }, if odd_v { s } else { 0 });
    let p = (hf.raw_at(sx - dx, sz - dz) + hf.raw_at(sx + dx, sz + dz)) * 0.5;
    morph_raw(p, raw, f)
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
