//! The traversal over resident tiles (SPEC section 8, "The bound under streaming" and
//! "Precision"). Positions are f64 in the world; the camera is re-expressed relative to
//! its nearest sample (an integer), so every box handed to the f32 camera code is small
//! and exact whatever the distance to the terrain's origin.
//!
//! A block splits while its error exceeds delta, as in memory ([`crate::lod::traversal`],
//! strict mode's block bound: `D * height_scale * world_to_pixels`, refined square by
//! square where that exceeds delta: [`block_error_px`]). Where it should
//! split but the finer tile is not held, it is drawn as it is, the tile is wanted with
//! the block's error / delta as its priority, and the block counts over the bound. Blocks
//! within the bound but above `prefetch * delta` want their finer tile too, at a lower
//! priority, so that it is there before it is needed.

use super::cache::{layout, root_lod, serving_tile, BlockSummary, HostCache, Resident, SUB};
use super::errors::{stale_factor, TileErrors};
use super::{Grid, TileKey};
use crate::lod::block::DrawBlock;
use crate::lod::block_cache::BoundedCache;
use crate::lod::camera::{angular_factor, distance_to_aabb, world_to_pixels, Camera};
use crate::lod::gie::ErrorMode;
use crate::lod::stitch::{strip_departure, StripDeviation};
use crate::lod::traversal::{stitch_blocks, LodAt, SparseLods};
use foldhash::{HashSet, HashSetExt};
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

    /// The view as a terrain held whole sees it (sample (0, 0) at the world's origin, f32):
    /// for audits against the terrain in memory.
    pub fn absolute(&self) -> Camera {
        Camera {
            position: self.position.as_vec3(),
            forward: self.forward,
            fovy: self.fovy,
            width: self.width,
            height: self.height,
            near: self.near,
        }
    }

    /// The sample nearest the camera (the origin of the relative frame) and the camera
    /// relative to it. A camera off the terrain takes the terrain's sample nearest it:
    /// the frame's offsets stay within the terrain's samples (i32 on the GPU), however far
    /// the camera (a spacing of 1e-9 put the default camera 1.8e11 samples away).
    pub fn relative(&self, grid: &Grid) -> ([i64; 2], Camera) {
        let [sx, sz] = grid.sample_of(self.position.x, self.position.z);
        let anchor = [
            sx.round().clamp(0.0, (grid.width - 1) as f64) as i64,
            sz.round().clamp(0.0, (grid.height - 1) as f64) as i64,
        ];
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

/// How a streamed frame chooses its blocks' LODs (`--lod`), as in memory
/// ([`crate::lod::traversal::LodSelect`]).
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub enum StreamedLod {
    /// The bound: a block splits while its error exceeds delta (the renderer's).
    #[default]
    Error,
    /// Every block at LOD 0 (the reference image), as far as the held tiles go.
    Full,
    /// Distance rings (the GeoMipMapping-style baseline): a block splits while the camera
    /// is nearer than `factor` times its side.
    Distance { factor: f32 },
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
    /// It should split but its finer tile is not held, or its stitched strip is over
    /// delta and the coarser neighbour cannot split.
    pub over: bool,
    /// Over because a neighbour more than `m` LODs coarser could not split (a
    /// T-junction: pinholes may show along that edge).
    pub t_junction: bool,
    /// Its exact deviation `D` and its vertices' range (raw units), from its tile.
    pub d: f32,
    pub lo: f32,
    pub hi: f32,
    /// Its error came from the errors activity's generation (`Some(true)`), or could have
    /// and came from its tile's summary (`Some(false)`: no generation shaded its tile, or
    /// the camera may have come inside its distance); `None`: LOD 0 (never split), the top
    /// tile's coarser blocks, or no generation at all.
    pub from_errors: Option<bool>,
}

impl Selection {
    /// Drawn blocks whose error came from the errors activity, and drawn blocks that
    /// could have taken it from there and took their tile summary's.
    pub fn drawn_bounded_by(&self) -> (usize, usize) {
        let count = |v: bool| self.blocks.iter().filter(|b| b.from_errors == Some(v)).count();
        (count(true), count(false))
    }
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
    /// Blocks outside the view frustum, and each one's LOD, place and lowest sample (raw
    /// units: occlusion culling checks the near plane against them).
    pub culled: usize,
    pub frustum_culled: Vec<(u32, u32, u32, f32)>,
    /// The top tile was held (else nothing is drawn and the frame is over the bound).
    pub complete: bool,
    /// The blocks as drawn: stitched to their neighbours (empty for a selection made
    /// without the stitching rule, the prefetch's look ahead).
    pub stitched: Vec<DrawBlock>,
    /// Blocks split because a finer neighbour's stitched strip exceeded delta, or would
    /// have met it in a T-junction.
    pub stitch_splits: usize,
    /// Drawn blocks that morph ([`super::morph`]; 0 before it runs).
    pub morphing: usize,
    /// Blocks visited whose error came from the errors activity's newest generation
    /// ([`TileErrors`]), and blocks that could have had one but took their tile
    /// summary's alone (no generation shaded their tile, or the camera may have moved
    /// inside their distance since). The top tile's blocks coarser than its level are
    /// in neither: their bound is always the summary's.
    pub errors_from_gpu: usize,
    pub errors_from_tiles: usize,
    /// The generation those errors came from (0: none), and the largest correction for
    /// the camera's move since that the selection applied (1: none).
    pub errors_generation: u64,
    pub errors_stale_worst: f32,
    /// That generation's GPU time, when the device has timestamps.
    pub errors_gpu_ms: Option<f64>,
}

impl Selection {
    /// Is this frame within the bound (every block that should split did)?
    pub fn within_bound(&self) -> bool {
        self.complete && self.over_bound == 0
    }
}

/// Relative world box of block `(lod, bx, bz)` between raw heights `lo` and `hi`.
pub(super) fn block_box(grid: &Grid, anchor: [i64; 2], lod: u32, bx: u32, bz: u32, lo: f32, hi: f32) -> (Vec3, Vec3) {
    let size = (grid.block_quads << lod) as i64;
    square_of_samples_box(grid, anchor, [i64::from(bx) * size, i64::from(bz) * size], size, lo, hi)
}

/// Relative world box of the square of `size` samples a side from sample `from`, between
/// raw heights `lo` and `hi`.
pub(crate) fn square_of_samples_box(
    grid: &Grid,
    anchor: [i64; 2],
    from: [i64; 2],
    size: i64,
    lo: f32,
    hi: f32,
) -> (Vec3, Vec3) {
    let (x0, z0) = (from[0] - anchor[0], from[1] - anchor[1]);
    let x = |s: i64| (s as f64 * grid.spacing[0]) as f32;
    let z = |s: i64| (s as f64 * grid.spacing[1]) as f32;
    let y = |h: f32| (f64::from(h) * grid.height_scale) as f32;
    (Vec3::new(x(x0), y(lo), z(z0)), Vec3::new(x(x0 + size), y(hi), z(z0 + size)))
}

/// The block's error bound in pixels (strict mode): `D * height_scale` projected from its
/// box, and where that exceeds delta, the largest of its squares' `D`s each projected from
/// its own box ([`BlockSummary::squares`]; the in-memory bound takes a distance for
/// each group). Both are sound: every sample of a square lies in the square's part of
/// the box, no nearer than the square's box, and within the whole box's angles.
fn block_error_px(height_scale: f64, cam: &Camera, s: &BlockSummary, (min, max): (Vec3, Vec3), delta: f32) -> f32 {
    let scale = height_scale as f32;
    let whole = s.d * scale * world_to_pixels(cam, min, max, delta);
    if whole <= delta {
        return whole;
    }
    let per_distance = scale * cam.kappa() * angular_factor(cam, min, max, delta);
    let mut worst = 0.0f32;
    for (i, sq) in s.squares.iter().enumerate() {
        let (lo, hi) = square_box(height_scale, (min, max), i % SUB, i / SUB, sq.min, sq.max);
        worst = worst.max(sq.d * per_distance / distance_to_aabb(cam.position, lo, hi).max(cam.near));
    }
    worst.min(whole)
}

/// The box of square `(sx, sz)` of a block whose box is `(min, max)`, between raw heights
/// `lo` and `hi`. The squares' edges: neighbours share theirs bit for bit, and the outer
/// ones are the box's own, so the squares cover the box; heights are scaled as the box's
/// are ([`block_box`]).
pub(super) fn square_box(
    height_scale: f64,
    (min, max): (Vec3, Vec3),
    sx: usize,
    sz: usize,
    lo: f32,
    hi: f32,
) -> (Vec3, Vec3) {
    let edge = |a: f32, b: f32, i: usize| if i == SUB { b } else { a + (b - a) * i as f32 / SUB as f32 };
    let y = |h: f32| (f64::from(h) * height_scale) as f32;
    (
        Vec3::new(edge(min.x, max.x, sx), y(lo), edge(min.z, max.z, sz)),
        Vec3::new(edge(min.x, max.x, sx + 1), y(hi), edge(min.z, max.z, sz + 1)),
    )
}

/// The error bound in pixels of a block's stitched strip along edge `e` (north, east,
/// south, west; [`DrawBlock::cells_across`]'s order): `D + departure` (the samples'
/// deviation from the block's own surface plus the strip's from it, [`strip_departure`])
/// projected from the block's box widened to the strip's heights, and where that exceeds
/// delta, square by square along that edge (the strip is the row of quads along it), each
/// with its own `D` and box.
fn strip_error_px(
    height_scale: f64,
    cam: &Camera,
    s: &BlockSummary,
    (e, dep): (usize, &StripDeviation),
    (min, max): (Vec3, Vec3),
    delta: f32,
) -> f32 {
    let scale = height_scale as f32;
    let whole = (s.d + dep.edge[e]) * scale * world_to_pixels(cam, min, max, delta);
    if whole <= delta {
        return whole;
    }
    let per_distance = scale * cam.kappa() * angular_factor(cam, min, max, delta);
    let along = |k: usize| match e {
        0 => (k, 0),
        1 => (SUB - 1, k),
        2 => (k, SUB - 1),
        _ => (0, k),
    };
    let mut worst = 0.0f32;
    for (k, (sx, sz)) in (0..SUB).map(along).enumerate() {
        let sq = &s.squares[sz * SUB + sx];
        let (lo, hi) = square_box(height_scale, (min, max), sx, sz, sq.min.min(dep.lo), sq.max.max(dep.hi));
        let d = s.edge_d[e][k] + dep.edge[e];
        worst = worst.max(d * per_distance / distance_to_aabb(cam.position, lo, hi).max(cam.near));
    }
    worst.min(whole)
}

/// What stitching has been measured to cost, per block configuration (camera-free).
pub type StripCache = BoundedCache<DrawBlock, StripDeviation>;

/// Selects the blocks of a frame from the tiles `cache` holds. With `strips`, the
/// selection is the one drawn (SPEC section 5, cracks): blocks are stitched to their
/// neighbours, and a block whose stitched strip along a coarser neighbour would exceed
/// delta, or meet it more than `m` LODs apart (a T-junction), makes that neighbour split;
/// repeated until neither happens. The strip's bound is `D + strip_departure` (the
/// block's deviation from the true surface plus the strip's exact departure from the
/// block's own surface, [`strip_departure`]), projected from the block's box. A neighbour
/// whose finer tile is not held stays, and the block is counted over the bound.
pub fn select(
    grid: &Grid,
    cache: &HostCache,
    view: &View,
    delta: f32,
    prefetch: f32,
    strips: Option<&StripCache>,
) -> Selection {
    select_by(grid, cache, view, (StreamedLod::Error, delta, ErrorMode::Strict), prefetch, strips, None)
}

/// [`select`] with the LOD chosen by `lod`. Under [`StreamedLod::Full`] and
/// [`StreamedLod::Distance`] a block splits where the rule says, whatever its error; one
/// that should split but whose finer tile is not held is drawn as it is and counted over,
/// and stitched strips split neighbours only to avoid T-junctions: as in memory, those
/// selections are not bounded by delta.
///
/// With `errors`, a block's error is the smaller of two sound bounds: its tile summary's
/// ([`block_error_px`]) and the errors activity's, computed for an earlier camera, corrected
/// for the camera's move ([`stale_factor`]) and its `kappa`, times the block's own angular
/// factor.
pub fn select_by(
    grid: &Grid,
    cache: &HostCache,
    view: &View,
    (lod, delta, mode): (StreamedLod, f32, ErrorMode),
    prefetch: f32,
    strips: Option<&StripCache>,
    errors: Option<&TileErrors>,
) -> Selection {
    let root = root_lod(grid);
    let top = serving_tile(grid, root, 0, 0);
    if !cache.contains(top) {
        let mut out = Selection { worst_factor: 1.0, ..Default::default() };
        out.wanted.push((top, f32::INFINITY));
        return out;
    }
    let mut t = Traverser::new(grid, cache, view, delta, prefetch);
    t.lod = lod;
    t.mode = mode;
    if let Some(e) = errors {
        let [ax, az] = grid.world_xz(t.anchor[0] as f64, t.anchor[1] as f64);
        let old = e.position - DVec3::new(ax, 0.0, az);
        // Rounded up: a move a little larger only weakens the claim.
        let moved = ((view.position - e.position).length() as f32) * (1.0 + 1e-6);
        t.errors = Some((e, old.as_vec3(), moved));
        t.out.errors_generation = e.generation;
        t.out.errors_gpu_ms = e.gpu_ms;
    }
    t.visit(vec![(root, 0, 0)]);
    if let Some(strips) = strips {
        t.stitch(strips);
    }
    t.finish()
}

/// One frame's traversal, split again where stitching asks ([`Traverser::stitch`]).
struct Traverser<'a> {
    grid: &'a Grid,
    cache: &'a HostCache,
    delta: f32,
    lod: StreamedLod,
    /// Strict (a bound) or the paper's estimate where the errors activity gives one.
    mode: ErrorMode,
    prefetch: f32,
    anchor: [i64; 2],
    cam: Camera,
    frustum: crate::lod::camera::Frustum,
    /// The errors activity's newest generation, its camera relative to the anchor, and
    /// how far the camera has moved since.
    errors: Option<(&'a TileErrors, Vec3, f32)>,
    /// Blocks that split whatever their error, for a finer neighbour's stitching.
    forced: HashSet<(u32, u32, u32)>,
    used: HashSet<TileKey>,
    kept: HashSet<TileKey>,
    out: Selection,
}

impl<'a> Traverser<'a> {
    fn new(grid: &'a Grid, cache: &'a HostCache, view: &View, delta: f32, prefetch: f32) -> Self {
        let (anchor, cam) = view.relative(grid);
        Traverser {
            grid,
            cache,
            delta,
            lod: StreamedLod::Error,
            mode: ErrorMode::Strict,
            prefetch,
            anchor,
            frustum: cam.frustum(),
            cam,
            errors: None,
            forced: HashSet::new(),
            used: HashSet::new(),
            kept: HashSet::new(),
            out: Selection { worst_factor: 1.0, complete: true, errors_stale_worst: 1.0, ..Default::default() },
        }
    }

    /// Visits the blocks on `stack` and their descendants: a block splits while its error
    /// exceeds delta (or it is forced) and its finer tile is held; else it is drawn.
    fn visit(&mut self, mut stack: Vec<(u32, u32, u32)>) {
        let (grid, cache, delta) = (self.grid, self.cache, self.delta);
        while let Some((lod, bx, bz)) = stack.pop() {
            let size = grid.block_quads << lod;
            if bx as usize * size >= grid.width - 1 || bz as usize * size >= grid.height - 1 {
                continue; // wholly outside the true extent
            }
            let key = serving_tile(grid, lod, bx, bz);
            let tile = cache.peek(key).expect("a block is visited only when its tile is held");
            self.used.insert(key);
            let s = tile.block(grid, lod, bx, bz);
            let (min, max) = block_box(grid, self.anchor, lod, bx, bz, s.min, s.max);
            if !self.frustum.intersects_aabb(min, max) {
                self.out.culled += 1;
                self.out.frustum_culled.push((lod, bx, bz, s.min));
                continue;
            }
            let mut error_px = block_error_px(grid.height_scale, &self.cam, &s, (min, max), delta);
            // Strict: the smaller of two bounds. The paper's estimate replaces the
            // summary's bound where the errors activity has one (its finer tile held).
            let (gpu, could) = match self.mode {
                ErrorMode::Strict => {
                    (self.gpu_error_px(key, (lod, bx, bz), (min, max)), lod > 0 && lod == u32::from(key.level))
                }
                // Its dropped vertices are the finer tile's (the top tile's, for blocks
                // coarser than the top level).
                ErrorMode::Paper => (
                    self.paper_error_px((lod, bx, bz), (min, max)),
                    lod > 0 && cache.contains(serving_tile(grid, lod - 1, 2 * bx, 2 * bz)),
                ),
            };
            let from_errors = match gpu {
                Some(gpu) => {
                    error_px = if self.mode == ErrorMode::Paper { gpu } else { error_px.min(gpu) };
                    self.out.errors_from_gpu += 1;
                    Some(true)
                }
                None if could => {
                    self.out.errors_from_tiles += 1;
                    self.errors.is_some().then_some(false)
                }
                None => None,
            };
            let should_split = lod > 0
                && match self.lod {
                    StreamedLod::Error => error_px > delta,
                    StreamedLod::Full => true,
                    StreamedLod::Distance { factor } => {
                        distance_to_aabb(self.cam.position, min, max) <= factor * (max.x - min.x)
                    }
                };
            let finer = (lod > 0).then(|| serving_tile(grid, lod - 1, 2 * bx, 2 * bz));
            let finer_held = finer.is_some_and(|k| cache.contains(k));
            // Forced to split: for a finer neighbour's stitching, or, with holes, to draw a
            // block holding voids at LOD 0, whose tile has them exactly (a coarser tile's
            // cut holes only approximately). Neither is over the bound when it cannot.
            let stitching = self.forced.contains(&(lod, bx, bz)) || (grid.holes && s.voids && lod > 0);
            if (should_split || stitching) && finer_held {
                for (cx, cz) in [(0, 0), (1, 0), (0, 1), (1, 1)] {
                    stack.push((lod - 1, 2 * bx + cx, 2 * bz + cz));
                }
                continue;
            }
            let over = should_split;
            // A neighbour's stitching needs the finer tile as much as the block's own error
            // (under the other rules a split the rule asks for, as much as stitching).
            let want = match self.lod {
                StreamedLod::Error if !stitching => error_px / delta,
                StreamedLod::Error => (error_px / delta).max(2.0),
                _ if should_split || stitching => 2.0,
                _ => 0.0,
            };
            if let Some(k) = finer.filter(|k| want > self.prefetch && grid.stores(*k)) {
                if finer_held {
                    self.kept.insert(k);
                } else {
                    self.out.wanted.push((k, want));
                }
            }
            self.out.blocks.push(Selected {
                lod,
                bx,
                bz,
                tile: key,
                error_px,
                over,
                t_junction: false,
                d: s.d,
                lo: s.lo,
                hi: s.hi,
                from_errors,
            });
        }
    }

    /// Block `(lod, bx, bz)`'s error from the errors activity's generation, at this
    /// camera: `None` if the generation did not shade its tile (or the block is one of
    /// the top tile's coarser ones), or the camera may have come inside its distance.
    fn gpu_error_px(&mut self, key: TileKey, (lod, bx, bz): (u32, u32, u32), bbox: (Vec3, Vec3)) -> Option<f32> {
        let (errors, old, moved) = self.errors?;
        // Heights scaled otherwise since (the exaggeration): every group's error and box
        // changed; the generation bounds nothing.
        if lod != u32::from(key.level) || lod == 0 || errors.height_scale != self.grid.height_scale {
            return None;
        }
        let per_side = self.grid.tile_quads / self.grid.block_quads;
        let (lx, lz) = (bx as usize - key.tx as usize * per_side, bz as usize - key.tz as usize * per_side);
        // Infinite where a group's D is past the half floats' range: no bound then.
        let raw = errors.block(key, lz * per_side + lx).filter(|e| e.is_finite())?;
        let stale = stale_factor(old, moved, bbox)?;
        self.out.errors_stale_worst = self.out.errors_stale_worst.max(stale);
        let kappa = self.cam.kappa() / errors.kappa;
        Some(raw * stale * kappa * angular_factor(&self.cam, bbox.0, bbox.1, self.delta))
    }

    /// The paper's error of block `(lod, bx, bz)` (box `bbox`) from the errors
    /// activity's generation ([`TileErrors::paper`]: eq. 4 over the finer levels shaded),
    /// corrected for the camera's move and its `kappa`; no angular factor (the paper's
    /// per-vertex distance stands for the projection).
    fn paper_error_px(&mut self, (lod, bx, bz): (u32, u32, u32), bbox: (Vec3, Vec3)) -> Option<f32> {
        let (errors, old, moved) = self.errors?;
        if errors.height_scale != self.grid.height_scale {
            return None;
        }
        let raw = errors.paper.get(&(lod, bx, bz)).map(|e| e.0).filter(|e| e.is_finite())?;
        let stale = stale_factor(old, moved, bbox)?;
        self.out.errors_stale_worst = self.out.errors_stale_worst.max(stale);
        Some(raw * stale * self.cam.kappa() / errors.kappa)
    }

    /// Stitches the selection as drawn and splits the coarser neighbours of blocks whose
    /// stitched strip exceeds delta or meets them in a T-junction, in place (their
    /// descendants visited like any block), until none is left; what cannot split leaves
    /// its finer neighbour over the bound.
    fn stitch(&mut self, strips: &StripCache) {
        let (grid, delta) = (self.grid, self.delta);
        let layout = layout(grid);
        let resident = Resident { grid, cache: self.cache };
        loop {
            let mut blocks: Vec<DrawBlock> =
                self.out.blocks.iter().map(|b| DrawBlock::new(b.lod, b.bx, b.bz)).collect();
            let lods = SparseLods::new(&layout, &blocks);
            stitch_blocks(&resident, &layout, &mut blocks, &lods);
            let mut split = HashSet::new();
            // Blocks over the bound if nothing more splits: their strip's error in pixels
            // (`None`: a T-junction).
            let mut overs = Vec::new();
            for (i, b) in blocks.iter().enumerate() {
                if b.coarser == [0; 4] {
                    // Drawn as its own surface: corners move only onto a coarser side
                    // neighbour's edge (`resolve_corners`).
                    continue;
                }
                let sel = &self.out.blocks[i];
                let s = self.cache.peek(sel.tile).expect("a drawn block's tile is held").block(grid, b.lod, b.bx, b.bz);
                let dep = strips.get_or_compute(*b, || strip_departure(&resident, &layout, b));
                let (lo, hi) = (s.min.min(dep.lo), s.max.max(dep.hi));
                let boxed = block_box(grid, self.anchor, b.lod, b.bx, b.bz, lo, hi);
                for (e, (nx, nz)) in b.cells_across().into_iter().enumerate() {
                    let px = strip_error_px(grid.height_scale, &self.cam, &s, (e, &dep), boxed, delta);
                    // The paper's mode has no strip term (as in memory): T-junctions only.
                    let strict = self.lod == StreamedLod::Error && self.mode == ErrorMode::Strict;
                    let over = strict && dep.edge[e] > 0.0 && px > delta;
                    let t_junction = b.coarser[e] > b.stride() << layout.m;
                    if !(over || t_junction) {
                        continue;
                    }
                    overs.push((i, over.then_some(px)));
                    let lod = lods.lod_at(nx, nz, b.lod);
                    if b.coarser[e] > 0 && lod > 0 {
                        let n = (lod as u32, (nx >> lod) as u32, (nz >> lod) as u32);
                        if self.forced.insert(n) {
                            split.insert(n);
                        }
                    }
                }
            }
            // The newly forced blocks are drawn now: visit them again (they split where
            // their finer tile is held), leaving every other block as it is.
            let again: Vec<(u32, u32, u32)> =
                self.out.blocks.iter().map(|b| (b.lod, b.bx, b.bz)).filter(|k| split.contains(k)).collect();
            let splits = again
                .iter()
                .any(|&(lod, bx, bz)| lod > 0 && self.cache.contains(serving_tile(grid, lod - 1, 2 * bx, 2 * bz)));
            if !splits {
                // Their finer tiles are wanted, as much as a block's own error would want them.
                for &(lod, bx, bz) in &again {
                    let finer = serving_tile(grid, lod.saturating_sub(1), 2 * bx, 2 * bz);
                    if lod > 0 && grid.stores(finer) {
                        self.out.wanted.push((finer, 2.0));
                    }
                }
                for (i, px) in overs {
                    let b = &mut self.out.blocks[i];
                    b.over = true;
                    match px {
                        Some(px) => b.error_px = b.error_px.max(px),
                        None => b.t_junction = true,
                    }
                }
                self.out.stitch_splits = self.forced.len();
                self.out.stitched = blocks;
                return;
            }
            self.out.blocks.retain(|b| !split.contains(&(b.lod, b.bx, b.bz)));
            self.visit(again);
        }
    }

    /// The selection, with its counts (over the bound, the worst factor) and tiles.
    fn finish(mut self) -> Selection {
        let out = &mut self.out;
        out.over_bound = out.blocks.iter().filter(|b| b.over).count();
        out.worst_factor = out.blocks.iter().filter(|b| b.over).map(|b| b.error_px / self.delta).fold(1.0, f32::max);
        out.used = self.used.into_iter().collect();
        out.used.sort();
        out.kept = self.kept.into_iter().collect();
        out.kept.sort();
        self.out
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::stream::cache::Square;

    /// A vertical deviation of `D` anywhere in a block's square `i` (the only one that
    /// deviates), between the square's own heights (each square at other heights),
    /// projects to no more pixels than the block's bound, from cameras close to each
    /// corner, above and beside the block, and far; near one corner, a deviation in the
    /// far corner is bounded well below the whole block's bound (what the squares are
    /// for). A bound that mixed the squares up (x for z), or took another square's
    /// heights, fails the first check.
    #[test]
    fn each_square_is_bounded_from_its_own_place() {
        let (side, d, delta) = (320.0f32, 4.0f32, 1.0f32);
        // Square i spans heights 4i..4i + 6: the block 0..4 (SUB^2 - 1) + 6.
        let square = |i: usize, d: f32| Square { d, min: 4.0 * i as f32 - d, max: 4.0 * i as f32 + 6.0 + d };
        let (lo, hi) = (0.0f32, 4.0 * (SUB * SUB - 1) as f32 + 6.0);
        let (min, max) = (Vec3::new(0.0, lo - d, 0.0), Vec3::new(side, hi + d, side));
        let cameras = cameras_around(side);
        let (mut checked, mut tighter) = (0usize, 0usize);
        for cam in &cameras {
            let vp = cam.view_proj();
            for i in 0..SUB * SUB {
                let mut squares = std::array::from_fn(|j| square(j, 0.0));
                squares[i] = square(i, d);
                let s =
                    BlockSummary { lo, hi, d, min: lo - d, max: hi + d, squares, edge_d: [[d; SUB]; 4], voids: false };
                let bound = block_error_px(1.0, cam, &s, (min, max), delta);
                let whole = d * world_to_pixels(cam, min, max, delta);
                assert!(bound <= whole, "never looser than the whole block's");
                let step = side / SUB as f32;
                let (x0, z0) = ((i % SUB) as f32 * step, (i / SUB) as f32 * step);
                // A segment of length D between the square's heights.
                let heights = [squares[i].min, squares[i].max - d];
                for (u, v, y) in (0..=4).flat_map(|u| (0..=4).flat_map(move |v| heights.map(|y| (u, v, y)))) {
                    let p = Vec3::new(x0 + step * u as f32 / 4.0, y, z0 + step * v as f32 / 4.0);
                    let Some(px) = projected(cam, &vp, p, d) else { continue };
                    let at = cam.position;
                    assert!(
                        px <= bound * 1.0001,
                        "square {i}, camera at {at}: a deviation at {p} is {px} px, bound {bound}"
                    );
                    checked += 1;
                }
                tighter += usize::from(bound < 0.5 * whole);
            }
        }
        assert!(checked > 10_000, "{checked} deviations on screen");
        assert!(tighter > 100, "{tighter} squares bounded at under half the whole block's");
    }

    /// Cameras close to each corner of a `side`-wide block at the origin, low and high,
    /// looking at its middle and its corners, and one far above.
    fn cameras_around(side: f32) -> Vec<Camera> {
        let mut cameras = Vec::new();
        let (far, mid) = (side + 5.0, side / 2.0);
        for &(x, z) in &[(-5.0, -5.0), (far, -5.0), (-5.0, far), (far, far), (mid, -40.0)] {
            for &y in &[2.0f32, 20.0, 60.0, 400.0] {
                for &(tx, tz) in &[(mid, mid), (0.0, 0.0), (side, 0.0), (0.0, side), (side, side)] {
                    cameras.push(Camera::look_at(Vec3::new(x, y, z), Vec3::new(tx, 10.0, tz), 45.0, 640, 480, 0.5));
                }
            }
        }
        let above = Vec3::new(mid, 3000.0, mid + 10.0);
        cameras.push(Camera::look_at(above, Vec3::new(mid, 0.0, mid), 45.0, 640, 480, 0.5));
        cameras
    }

    /// The pixels a vertical segment of `length` from `p` up spans, when both its ends
    /// are on the screen.
    fn projected(cam: &Camera, vp: &glam::Mat4, p: Vec3, length: f32) -> Option<f32> {
        let on_screen = |q: Option<(f32, f32)>| {
            q.filter(|&(x, y)| (0.0..=cam.width as f32).contains(&x) && (0.0..=cam.height as f32).contains(&y))
        };
        let (a, b) = (on_screen(cam.project(vp, p))?, on_screen(cam.project(vp, p + Vec3::Y * length))?);
        Some(((a.0 - b.0).powi(2) + (a.1 - b.1).powi(2)).sqrt())
    }

    /// A stitched strip's deviation (`D` of the edge's row of groups over a square plus
    /// the strip's departure) anywhere on that row projects to no more pixels than the
    /// strip's bound, for each edge and each square along it in turn, from the same
    /// cameras; the bound is never looser than the whole block's. A bound that took the
    /// squares along the opposite edge, or another edge's row, fails it.
    #[test]
    fn a_strip_is_bounded_from_the_squares_along_its_edge() {
        let (side, delta) = (320.0f32, 1.0f32);
        let quad = side / crate::stream::DEFAULT_BLOCK_QUADS as f32;
        let square = |i: usize, d: f32| Square { d, min: 3.0 * i as f32 - d, max: 3.0 * i as f32 + 5.0 + d };
        let (lo, hi, d, departure) = (0.0f32, 3.0 * (SUB * SUB - 1) as f32 + 5.0, 3.0f32, 2.0f32);
        let (mut checked, mut tighter) = (0usize, 0usize);
        for cam in &cameras_around(side) {
            let vp = cam.view_proj();
            for e in 0..4 {
                let mut dep = StripDeviation { edge: [0.0; 4], lo: lo - 1.0, hi: hi + 1.0 };
                dep.edge[e] = departure;
                let (min, max) = (Vec3::new(0.0, lo - d - 1.0, 0.0), Vec3::new(side, hi + d + 1.0, side));
                for k in 0..SUB {
                    let (sx, sz) = match e {
                        0 => (k, 0),
                        1 => (SUB - 1, k),
                        2 => (k, SUB - 1),
                        _ => (0, k),
                    };
                    let mut squares = std::array::from_fn(|j| square(j, 0.0));
                    squares[sz * SUB + sx] = square(sz * SUB + sx, d);
                    // Only this square's part of the edge's row deviates.
                    let mut edge_d = [[0.0; SUB]; 4];
                    edge_d[e][k] = d;
                    let s = BlockSummary { lo, hi, d, min: lo - d, max: hi + d, squares, edge_d, voids: false };
                    let bound = strip_error_px(1.0, cam, &s, (e, &dep), (min, max), delta);
                    let whole = (d + departure) * world_to_pixels(cam, min, max, delta);
                    assert!(bound <= whole);
                    tighter += usize::from(bound < 0.5 * whole);
                    // Points along the edge over the square, on the row of quads along it.
                    let step = side / SUB as f32;
                    let sq = &s.squares[sz * SUB + sx];
                    let (y0, y1) = (sq.min.min(dep.lo), sq.max.max(dep.hi) - (d + departure));
                    for (t, inward, y) in (0..=8)
                        .flat_map(|t| [0.0, quad].into_iter().flat_map(move |w| [y0, y1].map(move |y| (t, w, y))))
                    {
                        let run = k as f32 * step + step * t as f32 / 8.0;
                        let (x, z) = match e {
                            0 => (run, inward),
                            1 => (side - inward, run),
                            2 => (run, side - inward),
                            _ => (inward, run),
                        };
                        let p = Vec3::new(x, y, z);
                        let Some(px) = projected(cam, &vp, p, d + departure) else { continue };
                        assert!(
                            px <= bound * 1.0001,
                            "edge {e}, square {k}, camera at {}: {px} px at {p}, bound {bound}",
                            cam.position
                        );
                        checked += 1;
                    }
                }
            }
        }
        assert!(checked > 5_000, "{checked} deviations on screen");
        assert!(tighter > 50, "{tighter} strips bounded at under half the whole block's");
    }
}
