//! Blocks (SPEC section 5): the layout of the quadtree's blocks, the block a frame draws
//! (LOD, neighbours, corners, morph factors), the selection a traversal produces, and the
//! vertex shader's placement of a block's vertices in plain Rust.

use crate::lod::camera::{Camera, Frustum};
use crate::lod::heightfield::{Heightfield, RawSamples};
use crate::lod::pyramid::MinMaxPyramid;
use glam::Vec3;

/// Block geometry: `k = 2^m + 1` vertices a side; a block of LOD `j` covers `2^(m+j)`
/// samples; each of the heightfield's roots is one block at LOD `n - m`.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct BlockLayout {
    pub n: u32,
    pub m: u32,
    /// Roots along x and z (the heightfield's).
    pub roots: [usize; 2],
}

impl BlockLayout {
    /// The `m` of a block side `k`: `k` must be `2^m + 1` with `m >= 1`, at most 257.
    pub fn check(k: u32) -> Result<u32, String> {
        if k < 3 || !(k - 1).is_power_of_two() {
            return Err(format!(
                "--block {k}: the block side must be 2^m + 1 (3, 5, 9, 17, 33, 65, ...; 9 to 129 for a terrain drawn from tiles)"
            ));
        }
        if k > 257 {
            return Err(format!(
                "--block {k}: at most 257 (vertex coordinates are 8-bit; 129 for a terrain drawn from tiles)"
            ));
        }
        Ok((k - 1).trailing_zeros())
    }

    /// The layout of blocks of side `k` over `hf`; a block larger than a root is shrunk
    /// to the root.
    pub fn of(hf: &Heightfield, k: u32) -> Result<Self, String> {
        Ok(BlockLayout { n: hf.n, m: Self::check(k)?.min(hf.n), roots: hf.roots })
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
    /// Cells of the finest block grid (LOD 0 blocks) along x and z: `roots << (n - m)`.
    pub fn cells(&self) -> [usize; 2] {
        [self.roots[0] << self.root_lod(), self.roots[1] << self.root_lod()]
    }

    /// Blocks of LOD `lod` along x and z.
    pub fn blocks(&self, lod: u32) -> [usize; 2] {
        [self.roots[0] << (self.root_lod() - lod), self.roots[1] << (self.root_lod() - lod)]
    }
    /// Triangles in one block.
    pub fn triangles_per_block(&self) -> u64 {
        let q = (self.k() - 1) as u64;
        2 * q * q
    }
    /// Parts along each side of a block ([`parts_per_side`]).
    pub fn parts_per_side(&self) -> u32 {
        parts_per_side(self.m)
    }
    /// Triangles in one part of a block.
    pub fn triangles_per_part(&self) -> u64 {
        let p = self.parts_per_side() as u64;
        self.triangles_per_block() / (p * p)
    }
    /// Bits of [`DrawBlock::hidden_parts`] that name a part: all set, the whole block.
    pub fn all_parts(&self) -> u16 {
        let p = self.parts_per_side();
        ((1u32 << (p * p)) - 1) as u16
    }
}

/// Vertices a side of a block unless `--block` says otherwise: the paper's k = 33.
pub const DEFAULT_K: u32 = 33;

/// Parts along each side of a block of `2^m` quads: the squares occlusion culling hides
/// one by one, each a contiguous range of the block mesh's indices ([`block_mesh_data`]).
/// Each part is an even number of quads wide, so a vertex that morphs towards its parent
/// surface and the two samples it morphs between lie in the same part.
pub fn parts_per_side(m: u32) -> u32 {
    match m {
        0 | 1 => 1,
        2 => 2,
        _ => 4,
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
/// west (-x), and its geomorph (see [`crate::lod::morph`]).
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
    /// Parts of the block that occlusion culling found hidden and the renderer leaves
    /// out: bit `pz * p + px` for part `(px, pz)` of the `p x p` parts
    /// ([`parts_per_side`]). Not part of what the block is: [`DrawBlock::unmorphed`]
    /// (the caches' key) clears it.
    pub hidden_parts: u16,
}

/// A corner whose height is its sample's (blocks made outside the traversal).
pub const CORNER_UNRESOLVED: u32 = u32::MAX;

/// The corners at the start and the end of each edge (north, east, south, west), in the
/// direction of increasing x or z.
pub const EDGE_CORNERS: [[usize; 2]; 4] = [[0, 1], [1, 2], [3, 2], [0, 3]];

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
            hidden_parts: 0,
        }
    }
    /// Raw height of corner `c` at sample `(x, z)`.
    pub fn corner<S: RawSamples + ?Sized>(&self, c: usize, hf: &S, x: i64, z: i64) -> f32 {
        match self.corner_raw[c] {
            CORNER_UNRESOLVED => hf.raw_at(x, z),
            bits => f32::from_bits(bits),
        }
    }
    /// The block with every vertex at its own LOD (factor 1): the surface the selection
    /// bounds.
    pub fn unmorphed(&self) -> Self {
        DrawBlock { morph: MORPH_ONE, edge_morph: [MORPH_ONE; 4], hidden_parts: 0, ..*self }
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

/// Why a frame was not occlusion-culled.
#[derive(Clone, Copy, Debug, PartialEq, Eq, serde::Serialize)]
#[serde(rename_all = "snake_case")]
pub enum Skipped {
    /// `--voids hole`: the surface has openings a ray can pass through.
    Holes,
    /// The camera is not over the terrain's true extent.
    CameraOutside,
    /// The near plane touches or dips under the drawn surface.
    NearPlaneLow,
    /// A drawn block beside a frustum-culled one is `m` or more LODs coarser.
    CoarseBesideCulled,
    /// Not run this frame: the last run hid too little to pay for itself
    /// (`occlusion::Probe`).
    Paused,
    /// A drawn block's tile is not held (a terrain drawn from tiles): its surface is
    /// not known to be drawn.
    TileMissing,
}

impl Skipped {
    pub fn as_str(self) -> &'static str {
        match self {
            Skipped::Holes => "holes",
            Skipped::CameraOutside => "camera outside the terrain",
            Skipped::NearPlaneLow => "near plane at the ground",
            Skipped::CoarseBesideCulled => "coarse block beside a culled one",
            Skipped::Paused => "paused: hid too little",
            Skipped::TileMissing => "a drawn block's tile not held",
        }
    }
}

/// What occlusion culling did in one frame.
#[derive(Clone, Copy, Debug, Default, PartialEq, serde::Serialize)]
pub struct OcclusionReport {
    /// Blocks of the selection tested.
    pub tested: usize,
    /// Blocks found hidden (moved to `Traversal::occluded`).
    pub hidden: usize,
    /// Parts of the tested blocks ([`parts_per_side`] squared each).
    pub tested_parts: usize,
    /// Parts found hidden, those of hidden blocks included.
    pub hidden_parts: usize,
    /// Set when the frame was not culled.
    pub skipped: Option<Skipped>,
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
    /// Blocks of the selection that no pixel can see (`lod::occlusion`): not drawn, but
    /// still selected at their LOD, so that their neighbours stitch to it and the audit
    /// covers their samples. Empty unless occlusion culling ran.
    pub occluded: Vec<DrawBlock>,
    /// Blocks the frustum culled (what occlusion culling checks its argument against).
    pub frustum_culled: Vec<DrawBlock>,
    /// Parts of drawn blocks left out because they lie outside the frustum
    /// ([`hide_parts_outside`]; 0 until it runs).
    pub frustum_parts: usize,
    /// What occlusion culling did, when it ran.
    pub occlusion: Option<OcclusionReport>,
}

impl Traversal {
    /// Every selected block: the drawn ones, then the occluded ones.
    pub fn selection(&self) -> impl Iterator<Item = &DrawBlock> + '_ {
        self.blocks.iter().chain(&self.occluded)
    }
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
    let s = layout.block_samples(lod) as i64;
    let [lo, hi] = mm.get(level, bx as usize, bz as usize);
    let (x0, z0) = (bx as i64 * s, bz as i64 * s);
    hf.world_box(x0, z0, x0 + s, z0 + s, [lo * hf.height_scale, hi * hf.height_scale])
}

/// LOD of the drawn block over each finest-grid cell (-1: nothing drawn there).
pub fn lod_map(layout: &BlockLayout, blocks: &[DrawBlock]) -> Vec<i8> {
    let [cells, rows] = layout.cells();
    let mut map = vec![-1i8; cells * rows];
    for b in blocks {
        let span = 1usize << b.lod;
        let (cx, cz) = (b.bx as usize * span, b.bz as usize * span);
        for z in cz..cz + span {
            map[z * cells + cx..z * cells + cx + span].fill(b.lod as i8);
        }
    }
    map
}

/// The vertex shader's placement of block vertex `(u, v)`, in plain Rust: the sample it
/// lands on and its raw height, stitched and morphed (SPEC section 5). Must match
/// `glsl/block_vertex.glsl` bit for bit.
pub fn block_vertex<S: RawSamples + ?Sized>(
    hf: &S,
    layout: &BlockLayout,
    b: &DrawBlock,
    u: u32,
    v: u32,
) -> (i64, i64, f32) {
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
/// are given ([`crate::lod::morph`]), between the mean of the two vertices around it along
/// the edge and their own sample. The neighbour's origin is a multiple of twice its
/// stride, so a vertex's parity is that of its coordinate over the stride.
fn coarse_vertex_raw<S: RawSamples + ?Sized>(hf: &S, b: &DrawBlock, side: usize, sx: i64, sz: i64) -> f32 {
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
fn own_vertex_raw<S: RawSamples + ?Sized>(hf: &S, b: &DrawBlock, last: u32, u: u32, v: u32, sx: i64, sz: i64) -> f32 {
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

/// A part of a drawn block ([`parts_per_side`]) as culling tests it.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct PartBox {
    /// Its bit of [`DrawBlock::hidden_parts`].
    pub bit: u16,
    /// Its square of samples: from `(x0, z0)`, `size` samples on a side.
    pub x0: i64,
    pub z0: i64,
    pub size: i64,
    /// The lowest and highest raw height of its triangles' vertices.
    pub raw: [f32; 2],
}

/// The parts of `b` that can be left out alone, with their boxes. A part's triangles are
/// its own quads', whose vertices lie over its square between its samples' lowest and
/// highest (a vertex morphs towards the mean of two samples of its own part: each part is
/// an even number of quads wide), or at a resolved corner's height. Parts along an edge
/// that follows a coarser neighbour are not listed: the stitched triangles fan past the
/// part along that edge, so they go only with their whole block.
pub fn part_boxes<'a>(
    mm: &'a MinMaxPyramid,
    layout: &BlockLayout,
    b: &'a DrawBlock,
) -> impl Iterator<Item = PartBox> + 'a {
    let p = layout.parts_per_side();
    let level = layout.m + b.lod - p.trailing_zeros();
    part_boxes_by(layout, b, move |px, pz| mm.get(level, (b.bx * p + px) as usize, (b.bz * p + pz) as usize))
}

/// [`part_boxes`] with each part's raw height range from `raw(px, pz)` (the part's
/// column and row in its block): the range of its samples, from wherever the caller
/// keeps them (the in-memory pyramid; a streamed tile's summaries).
pub fn part_boxes_by<'a>(
    layout: &BlockLayout,
    b: &'a DrawBlock,
    raw: impl Fn(u32, u32) -> [f32; 2] + 'a,
) -> impl Iterator<Item = PartBox> + 'a {
    let p = layout.parts_per_side();
    let level = layout.m + b.lod - p.trailing_zeros();
    let size = 1i64 << level;
    let corner_part = [(0, 0), (p - 1, 0), (p - 1, p - 1), (0, p - 1)];
    let parts = if p > 1 { 0..p * p } else { 0..0 };
    parts.filter_map(move |part| {
        let (px, pz) = (part % p, part / p);
        let on_edge = [pz == 0, px == p - 1, pz == p - 1, px == 0];
        if (0..4).any(|e| on_edge[e] && b.coarser[e] > 0) {
            return None;
        }
        let (x, z) = (b.bx * p + px, b.bz * p + pz);
        let mut raw = raw(px, pz);
        for (c, _) in corner_part.iter().enumerate().filter(|(_, &cp)| cp == (px, pz)) {
            if b.corner_raw[c] != CORNER_UNRESOLVED {
                let h = f32::from_bits(b.corner_raw[c]);
                raw = [raw[0].min(h), raw[1].max(h)];
            }
        }
        Some(PartBox { bit: 1 << part, x0: x as i64 * size, z0: z as i64 * size, size, raw })
    })
}

/// Margin, in pixels beyond the image's edges, of the frustum that culls parts: a part
/// is left out only when its box lies wholly beyond it, so that rounding in the vertex
/// shader cannot bring one of its triangles onto a pixel centre.
pub const PART_FRUSTUM_MARGIN_PX: f32 = 1.0;

/// The parts of `b` ([`part_boxes`]) whose boxes lie wholly outside `frustum`, as bits of
/// [`DrawBlock::hidden_parts`]: no pixel of the frame can show them.
pub fn parts_outside(
    hf: &Heightfield,
    mm: &MinMaxPyramid,
    layout: &BlockLayout,
    frustum: &Frustum,
    b: &DrawBlock,
) -> u16 {
    let hs = hf.height_scale;
    part_boxes(mm, layout, b)
        .filter(|pb| {
            let (x1, z1) = (pb.x0 + pb.size, pb.z0 + pb.size);
            let (min, max) = hf.world_box(pb.x0, pb.z0, x1, z1, [pb.raw[0] * hs, pb.raw[1] * hs]);
            !frustum.intersects_aabb(min, max)
        })
        .fold(0, |hidden, pb| hidden | pb.bit)
}

/// Leaves out of every drawn block of `t` the parts outside `cam`'s frustum widened by
/// [`PART_FRUSTUM_MARGIN_PX`] ([`parts_outside`]); returns how many parts that hid.
/// Blocks stay in the selection, whatever they hide, so that nothing else changes.
pub fn hide_parts_outside(
    hf: &Heightfield,
    mm: &MinMaxPyramid,
    layout: &BlockLayout,
    cam: &Camera,
    t: &mut Traversal,
) -> usize {
    let frustum = cam.frustum_widened(PART_FRUSTUM_MARGIN_PX);
    let mut hidden = 0;
    for b in &mut t.blocks {
        let outside = parts_outside(hf, mm, layout, &frustum, b) & !b.hidden_parts;
        hidden += outside.count_ones() as usize;
        b.hidden_parts |= outside;
    }
    t.frustum_parts = hidden;
    hidden
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

/// The quads of a block of side `k` in the order of [`block_mesh_data`]'s indices: part
/// by part ([`parts_per_side`], rows of parts, then the part's rows of quads).
pub fn quad_order(k: u32) -> Vec<(u32, u32)> {
    let q = k - 1;
    let p = parts_per_side(q.trailing_zeros());
    let side = q / p;
    let mut quads = Vec::with_capacity((q * q) as usize);
    for part in 0..p * p {
        let (px, pz) = (part % p, part / p);
        for v in pz * side..(pz + 1) * side {
            for u in px * side..(px + 1) * side {
                quads.push((u, v));
            }
        }
    }
    quads
}

/// The triangles of the quads on the outer ring of the block mesh `idx` (side `k`, as
/// [`block_mesh_data`] makes it: six indices a quad, in [`quad_order`]).
pub fn ring_indices(idx: &[u32], k: u32) -> Vec<u32> {
    let q = k - 1;
    let order = quad_order(k);
    assert_eq!(idx.len(), order.len() * 6, "a block mesh of side {k}");
    (idx.chunks(6).zip(order))
        .filter(|(_, (u, v))| *u == 0 || *v == 0 || *u == q - 1 || *v == q - 1)
        .flat_map(|(t, _)| t.iter().copied())
        .collect()
}

/// Vertex bytes (u, v) and indices of a k x k block: the one mesh every block is drawn
/// from, each quad split along its a-i diagonal (triangles a-c-i and a-i-g), the quads in
/// [`quad_order`] so that each part of the block is one range of indices.
pub fn block_mesh_data(k: u32) -> (Vec<u8>, Vec<u32>) {
    let mut verts = Vec::with_capacity((k * k * 2) as usize);
    for v in 0..k {
        for u in 0..k {
            verts.push(u as u8);
            verts.push(v as u8);
        }
    }
    let mut idx = Vec::with_capacity(((k - 1) * (k - 1) * 6) as usize);
    for (u, v) in quad_order(k) {
        let a = v * k + u;
        let c = a + 1;
        let g = a + k;
        let i = g + 1;
        idx.extend_from_slice(&[a, c, i, a, i, g]);
    }
    (verts, idx)
}

/// `f` over `items` in order: on every thread of the rayon pool the caller runs in
/// (`ThreadPool::install`), or on the calling thread alone when it runs in none. The
/// draw thread installs its traversal in a pool on a GPU and runs it on itself on a CPU
/// device, where rayon's workers would take cycles from the rasterizer's threads
/// (docs/benchmarks.md, "On a GPU"); the results are the same either way.
/// The traversal's worker threads for [`map_in_pool`] (`--traversal-threads`): a rayon
/// pool of its own, or none for one thread (the caller's: the draw thread, the
/// streamer's frame).
#[derive(Default)]
pub struct TraversalPool(Option<rayon::ThreadPool>);

impl TraversalPool {
    /// `threads` workers named `traverse-i` (1 or 0: none, the calling thread alone).
    pub fn new(threads: usize) -> Result<Self, String> {
        if threads <= 1 {
            return Ok(TraversalPool(None));
        }
        rayon::ThreadPoolBuilder::new()
            .num_threads(threads)
            .thread_name(|i| format!("traverse-{i}"))
            .build()
            .map(|p| TraversalPool(Some(p)))
            .map_err(|e| format!("the traversal's {threads} threads: {e}"))
    }

    /// How many threads run [`map_in_pool`] inside [`TraversalPool::install`].
    pub fn threads(&self) -> usize {
        self.0.as_ref().map_or(1, |p| p.current_num_threads())
    }

    /// Runs `f` with [`map_in_pool`] spreading over this pool's threads.
    pub fn install<R: Send>(&self, f: impl FnOnce() -> R + Send) -> R {
        match &self.0 {
            Some(pool) => pool.install(f),
            None => f(),
        }
    }
}

pub fn map_in_pool<T: Sync, R: Send>(items: &[T], f: impl Fn(usize, &T) -> R + Sync + Send) -> Vec<R> {
    use rayon::prelude::*;
    if rayon::current_thread_index().is_some() {
        items.par_iter().enumerate().map(|(i, v)| f(i, v)).collect()
    } else {
        items.iter().enumerate().map(|(i, v)| f(i, v)).collect()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Vertices of each listed part's triangles that fall outside its box ([`part_boxes`]
    /// computed for `boxed`, placed for `b`), over every part of the index ranges.
    fn part_box_escapes(
        hf: &Heightfield,
        mm: &MinMaxPyramid,
        layout: &BlockLayout,
        b: &DrawBlock,
        boxed: &DrawBlock,
    ) -> usize {
        let (_, idx) = block_mesh_data(layout.k());
        let p = layout.parts_per_side();
        let per_part = idx.len() / (p * p) as usize;
        let mut escapes = 0;
        for pb in part_boxes(mm, layout, boxed) {
            let part = pb.bit.trailing_zeros() as usize;
            for &i in &idx[part * per_part..(part + 1) * per_part] {
                let (u, v) = (i % layout.k(), i / layout.k());
                let (sx, sz, raw) = block_vertex(hf, layout, b, u, v);
                let inside = (pb.x0..=pb.x0 + pb.size).contains(&sx)
                    && (pb.z0..=pb.z0 + pb.size).contains(&sz)
                    && (pb.raw[0]..=pb.raw[1]).contains(&raw);
                escapes += usize::from(!inside);
            }
        }
        escapes
    }

    /// Every vertex of a listed part's triangles lies in its box (what makes culling a part
    /// by its box conservative), for blocks beside neighbours 1 to m LODs coarser (whose
    /// edge vertices collapse up to half a neighbour's segment away), every morph factor
    /// and resolved corners, over rough noise (where a part's neighbours' samples are
    /// far outside its own range). Mutation: boxes made as if no neighbour were coarser
    /// let the stitched vertices escape.
    #[test]
    fn part_boxes_hold_their_triangles() {
        let n = 257usize;
        let mut s = 0x9e37_79b9_u64;
        let samples: Vec<f32> = (0..n * n)
            .map(|_| {
                s = s.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
                (s >> 40) as f32 / (1u64 << 24) as f32 * 100.0
            })
            .collect();
        let hf = Heightfield::embed("noise", n, n, &samples, crate::lod::heightfield::HeightFormat::Float32, 1.0, 1.0)
            .unwrap();
        let mm = MinMaxPyramid::build(&hf);
        let layout = BlockLayout::of(&hf, 17).unwrap();
        let (mut listed, mut escaped_when_unstitched) = (0, 0);
        let mut rng = |k: u32| {
            s = s.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
            ((s >> 33) % k as u64) as u32
        };
        for lod in 0..3u32 {
            let blocks_per_side = (n as u32 - 1) / layout.block_samples(lod);
            for _ in 0..60 {
                let mut b = DrawBlock::new(lod, rng(blocks_per_side), rng(blocks_per_side));
                for e in 0..4 {
                    // A neighbour 1 to m LODs coarser on about half the edges.
                    if rng(2) == 0 {
                        b.coarser[e] = 1 << (lod + 1 + rng(layout.m));
                    }
                    b.edge_morph[e] = rng(MORPH_ONE as u32 + 1) as u16;
                }
                b.morph = rng(MORPH_ONE as u32 + 1) as u16;
                for c in 0..4 {
                    if rng(3) == 0 {
                        b.corner_raw[c] = (rng(1000) as f32 * 0.1).to_bits();
                    }
                }
                listed += part_boxes(&mm, &layout, &b).count();
                assert_eq!(part_box_escapes(&hf, &mm, &layout, &b, &b), 0, "{b:?}");
                let unstitched = DrawBlock { coarser: [0; 4], ..b };
                escaped_when_unstitched += part_box_escapes(&hf, &mm, &layout, &b, &unstitched);
            }
        }
        assert!(listed >= 1000, "only {listed} parts listed");
        assert!(escaped_when_unstitched > 0, "mutation: boxes blind to coarser neighbours went unnoticed");
    }

    /// Every quad once; each part's range of the indices holds exactly the quads of that
    /// part's square, and each part is an even number of quads wide (the morph argument
    /// of occlusion culling's part boxes needs it).
    #[test]
    fn each_part_is_one_range_of_the_mesh() {
        for m in 1..=8 {
            let k = (1u32 << m) + 1;
            let (_, idx) = block_mesh_data(k);
            let q = k - 1;
            let p = parts_per_side(m);
            assert!(p == 1 || (q / p).is_multiple_of(2), "k {k}: parts of {} quads", q / p);
            let per_part = (q * q / (p * p) * 6) as usize;
            assert_eq!(idx.len(), per_part * (p * p) as usize);
            let mut seen = vec![false; (q * q) as usize];
            for (part, range) in idx.chunks(per_part).enumerate() {
                let (px, pz) = (part as u32 % p, part as u32 / p);
                let side = q / p;
                for quad in range.chunks(6) {
                    // a is the quad's lowest vertex: (u, v) = (a % k, a / k).
                    let (u, v) = (quad[0] % k, quad[0] / k);
                    assert_eq!(quad, [quad[0], quad[0] + 1, quad[0] + k + 1, quad[0], quad[0] + k + 1, quad[0] + k]);
                    assert_eq!((u / side, v / side), (px, pz), "k {k}: quad ({u}, {v}) in part {part}");
                    assert!(!std::mem::replace(&mut seen[(v * q + u) as usize], true), "k {k}: quad ({u}, {v}) twice");
                }
            }
            assert!(seen.iter().all(|&s| s), "k {k}: a quad is missing");
        }
    }

    /// The ring is the outer row of quads on every side, whatever the mesh's order.
    #[test]
    fn ring_is_the_outer_quads() {
        for k in [3u32, 5, 9, 33] {
            let (_, idx) = block_mesh_data(k);
            let ring = ring_indices(&idx, k);
            let q = k - 1;
            let outer = if q == 1 { 1 } else { 4 * q - 4 };
            assert_eq!(ring.len(), outer as usize * 6, "k {k}");
            for quad in ring.chunks(6) {
                let (u, v) = (quad[0] % k, quad[0] / k);
                assert!(u == 0 || v == 0 || u == q - 1 || v == q - 1, "k {k}: ({u}, {v}) inside");
            }
        }
    }
}
