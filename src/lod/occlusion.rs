//! Occlusion culling that is provably conservative (SPEC section 10): of a frame's block
//! selection, the blocks that no pixel can see because nearer terrain covers them are
//! not drawn. They stay in the selection at their LOD (`Traversal::occluded`), so their
//! neighbours stitch to them as before and the audit still covers their samples.
//!
//! Why a culled block has no visible point. Inside the terrain's true extent (a
//! rectangle; the margin beyond it is never shown) the drawn surface is continuous and
//! lies, over each block, between that block's lowest and highest drawn vertex
//! ([`drawn_range`]). Take a ray from the camera, and a point `S` on it below the lowest
//! drawn vertex of some block `R`, inside `R`'s footprint. If the ray is above the surface
//! where it leaves the near plane, it must cross the surface between the near plane and
//! `S`: everything the ray meets after `S` is hidden. So a block `B` is culled when every
//! ray to every point of `B`'s box passes such an `S` first. Occluders are swept by
//! distance from the camera: a block's lowest drawn height, seen over the whole bin of
//! azimuth, gives an elevation below which every ray of that bin dips under it before
//! leaving its footprint (`horizon`); `B` is tested only against occluders it lies wholly
//! beyond. Elevations are compared with a margin of two pixels, so that rasterization's
//! snapping cannot uncover a culled block.
//!
//! What the argument needs, checked every frame (culling is skipped, with the reason,
//! when one fails): no holes (`--voids hole` opens the surface); the camera over the true
//! extent, so that the segment to any occluder stays over it; the near plane above the
//! drawn surface and above the lowest sample of every block the frustum culled near it. Then the first point
//! along a ray that is under terrain (under the drawn surface, or under the lowest sample
//! of a block the frustum culled) is a point of the drawn surface: the ray cannot enter a
//! culled block's column below its lowest sample from a neighbour's, because a drawn edge
//! beside a culled block interpolates vertices on that block's own edge, and it cannot
//! dip under that sample inside the column without meeting the block's box, which is
//! outside the frustum. That holds while no drawn block beside a culled one is `m` or more
//! LODs coarser (its edge's vertices, or its parent's, would lie beyond the culled
//! block's edge); such a frame is not culled either.

use crate::lod::block::{block_aabb, block_vertex, part_boxes, BlockLayout, DrawBlock, Traversal, CORNER_UNRESOLVED};
pub use crate::lod::block::{OcclusionReport, Skipped};
use crate::lod::camera::Camera;
use crate::lod::heightfield::Heightfield;
use crate::lod::morph::BlockCaches;
use crate::lod::pyramid::MinMaxPyramid;
use std::f64::consts::TAU;

/// Bins of azimuth around the camera over the full circle.
pub const BINS: usize = 4096;

/// When to run the sweep. It costs the draw thread about as much as a traversal, and
/// where nearly every block shows a sample (a high camera over rolling terrain) it hides
/// nothing; so after a run that did not pay ([`Probe::pays`]) it pauses
/// ([`Probe::pause_after`]), and runs every frame again once it pays.
///
/// Paying is judged by time once frames are timed (timestamps): the GPU time of the
/// triangles the sweep kept from the GPU against the sweep's own time on the draw
/// thread. On lavapipe a triangle costs about 100 ns and a sweep that hides 1 % of the
/// parts pays; on a discrete GPU it costs about 2 ns and the frame waits for the CPU:
/// there the same sweep costs a hundred times what it saves (docs/benchmarks.md, "On a
/// GPU"), and the pause keeps it under [`Probe::SHARE`] of the frames' time.
#[derive(Clone, Copy, Debug, Default)]
pub struct Probe {
    paused_for: u32,
    /// The latest timed frame: its GPU milliseconds and nanoseconds per triangle.
    timing: Option<(f64, f64)>,
}

impl Probe {
    /// Share of the tested parts a run must hide to run on the next frame, while no frame
    /// has been timed.
    pub const PAYS: f64 = 0.01;
    /// The least pause, in frames, after a run that did not pay.
    pub const EVERY: u32 = 8;
    /// Largest share of the frames' time that sweeps which do not pay may take.
    pub const SHARE: f64 = 0.05;
    /// The longest pause, in frames.
    pub const MAX_PAUSE: u32 = 256;

    /// A finished frame's GPU time and triangles (`None` where the queue has no
    /// timestamps): what a frame and a triangle cost from now on.
    pub fn observe(&mut self, gpu_ms: Option<f64>, triangles: u64) {
        if let (Some(ms), true) = (gpu_ms, triangles > 0) {
            self.timing = Some((ms, ms * 1e6 / triangles as f64));
        }
    }

    /// Frames to skip after a sweep of `sweep_ms` that did not pay: at least
    /// [`Probe::EVERY`], and enough that such sweeps take at most [`Probe::SHARE`] of
    /// the frames' time (a frame taken as long as its GPU time), up to
    /// [`Probe::MAX_PAUSE`].
    pub fn pause_after(sweep_ms: f64, frame_ms: Option<f64>) -> u32 {
        let frames = frame_ms.map_or(0.0, |f| sweep_ms / (Self::SHARE * f.max(1e-3)));
        (frames.ceil().min(Self::MAX_PAUSE as f64) as u32).max(Self::EVERY)
    }

    /// Whether a sweep that ran for `sweep_ms` paid: the GPU time of the triangles it
    /// kept from the GPU at `triangle_ns` each is at least its own time; with no timing,
    /// it hid at least [`Probe::PAYS`] of the parts.
    pub fn pays(report: &OcclusionReport, sweep_ms: f64, triangle_ns: Option<f64>, triangles_per_part: u64) -> bool {
        if report.skipped.is_some() {
            return false;
        }
        match triangle_ns {
            Some(ns) => report.hidden_parts as f64 * triangles_per_part as f64 * ns * 1e-6 >= sweep_ms,
            None => report.hidden_parts as f64 >= Self::PAYS * report.tested_parts.max(1) as f64,
        }
    }

    /// Culls `t` if this frame is due, and learns from the result.
    pub fn cull(
        &mut self,
        hf: &Heightfield,
        mm: &MinMaxPyramid,
        caches: &BlockCaches,
        layout: &BlockLayout,
        cam: &Camera,
        t: &mut Traversal,
    ) -> OcclusionReport {
        let tested = t.blocks.len();
        let report = self.run(tested, layout.triangles_per_part(), || cull(hf, mm, caches, layout, cam, t));
        t.occlusion = Some(report);
        report
    }

    /// Runs `sweep` (over `tested` blocks) if this frame is due, else reports it paused;
    /// learns from the result whether the next frame sweeps.
    pub fn run(
        &mut self,
        tested: usize,
        triangles_per_part: u64,
        sweep: impl FnOnce() -> OcclusionReport,
    ) -> OcclusionReport {
        if self.paused_for > 0 {
            self.paused_for -= 1;
            return OcclusionReport { tested, skipped: Some(Skipped::Paused), ..Default::default() };
        }
        let started = std::time::Instant::now();
        let report = sweep();
        let sweep_ms = started.elapsed().as_secs_f64() * 1e3;
        let paid = Self::pays(&report, sweep_ms, self.timing.map(|t| t.1), triangles_per_part);
        self.paused_for = if paid { 0 } else { Self::pause_after(sweep_ms, self.timing.map(|t| t.0)) - 1 };
        report
    }
}

/// World height range of everything drawn for `b`: its samples' range, widened by its
/// stitched strips, its edge regions in every morph state and its resolved corners (a
/// stitched edge follows a coarser neighbour's vertices, which can lie outside the
/// block's own range). Every drawn vertex of `b` lies in it, so the drawn surface over
/// `b`'s footprint does too (a test checks it against the drawn mesh).
pub fn drawn_range(
    hf: &Heightfield,
    mm: &MinMaxPyramid,
    caches: &BlockCaches,
    layout: &BlockLayout,
    b: &DrawBlock,
) -> [f32; 2] {
    let (min, max) = block_aabb(hf, mm, layout, b.lod, b.bx, b.bz);
    let (mut lo, mut hi) = (min.y, max.y);
    let hs = hf.height_scale;
    if b.coarser != [0; 4] {
        let strips = caches.stitch.get(hf, layout, b);
        lo = lo.min(strips.lo * hs);
        hi = hi.max(strips.hi * hs);
    }
    // No edge fixed: the range over every morph state of every edge.
    let regions = caches.stitch.regions_bound(hf, mm, layout, b, 0);
    lo = lo.min(regions.lo * hs);
    hi = hi.max(regions.hi * hs);
    for c in b.corner_raw.iter().filter(|&&c| c != CORNER_UNRESOLVED) {
        let h = f32::from_bits(*c) * hs;
        lo = lo.min(h);
        hi = hi.max(h);
    }
    [lo, hi]
}

/// A footprint on the ground, world x and z (f64: angles and distances are taken in f64).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Rect {
    pub x0: f64,
    pub z0: f64,
    pub x1: f64,
    pub z1: f64,
}

impl Rect {
    #[cfg(test)]
    fn contains(&self, x: f64, z: f64) -> bool {
        x >= self.x0 && x <= self.x1 && z >= self.z0 && z <= self.z1
    }

    /// Nearest and farthest horizontal distance from `(cx, cz)`.
    fn distances(&self, cx: f64, cz: f64) -> (f64, f64) {
        let near_x = (self.x0 - cx).max(cx - self.x1).max(0.0);
        let near_z = (self.z0 - cz).max(cz - self.z1).max(0.0);
        let far_x = (cx - self.x0).abs().max((self.x1 - cx).abs());
        let far_z = (cz - self.z0).abs().max((self.z1 - cz).abs());
        (near_x.hypot(near_z), far_x.hypot(far_z))
    }

    /// Azimuth interval `[a, b]` (radians, `a` in `[0, 2 pi)`, `b - a < pi`) covering the
    /// rectangle from a point outside it.
    fn azimuths(&self, cx: f64, cz: f64) -> (f64, f64) {
        let centre = ((self.z0 + self.z1) * 0.5 - cz).atan2((self.x0 + self.x1) * 0.5 - cx);
        let (mut lo, mut hi) = (0.0f64, 0.0f64);
        for (x, z) in [(self.x0, self.z0), (self.x1, self.z0), (self.x1, self.z1), (self.x0, self.z1)] {
            let mut d = (z - cz).atan2(x - cx) - centre;
            d -= TAU * (d / TAU).round();
            lo = lo.min(d);
            hi = hi.max(d);
        }
        let a = (centre + lo).rem_euclid(TAU);
        (a, a + (hi - lo))
    }

    /// Where a ray from `(cx, cz)` along the unit direction `(dx, dz)` leaves the
    /// rectangle (slab method; the ray is assumed to cross it).
    fn exit(&self, cx: f64, cz: f64, (dx, dz): (f64, f64)) -> f64 {
        let slab = |d: f64, c: f64, lo: f64, hi: f64| {
            if d > 0.0 {
                (hi - c) / d
            } else if d < 0.0 {
                (lo - c) / d
            } else {
                f64::INFINITY
            }
        };
        slab(dx, cx, self.x0, self.x1).min(slab(dz, cz, self.z0, self.z1))
    }
}

/// Unit directions of the bins' edges: edge `k` at azimuth `k * TAU / BINS`.
fn bin_edges() -> Vec<(f64, f64)> {
    (0..=BINS).map(|k| (k as f64 * TAU / BINS as f64).sin_cos()).map(|(s, c)| (c, s)).collect()
}

/// The nearest exit over bin `k` (wholly inside the rectangle's interval), given the
/// exits at its two edges: each slab's exit `K / |cos|` is least at an end of the bin or
/// where its direction cosine peaks, at a quarter turn, and quarter turns are bin edges
/// (`BINS` is a multiple of 4).
fn nearest_exit(at_edge_k: f64, at_edge_k1: f64) -> f64 {
    at_edge_k.min(at_edge_k1)
}

const _: () = assert!(BINS.is_multiple_of(4));

/// The highest drawn height of `b` over `rect`: exact from the vertices of the interior
/// quads under it (their triangles are the quads' own), or `whole` (the block's drawn
/// maximum) where `rect` reaches the edge strips, whose stitched triangles fan wider.
fn top_over(hf: &Heightfield, layout: &BlockLayout, b: &DrawBlock, rect: &Rect, whole: f64) -> f64 {
    let last = layout.k() as i64 - 1;
    let stride = b.stride() as f64;
    let (ox, oz) = b.origin(layout);
    let quad = |w: f64, spacing: f32, o: u32| ((w / spacing as f64 - o as f64) / stride).floor() as i64;
    let (u0, u1) = (quad(rect.x0, hf.spacing.x, ox), quad(rect.x1, hf.spacing.x, ox));
    let (v0, v1) = (quad(rect.z0, hf.spacing.z, oz), quad(rect.z1, hf.spacing.z, oz));
    if u0 < 1 || v0 < 1 || u1 > last - 2 || v1 > last - 2 {
        return whole;
    }
    let mut top = f64::NEG_INFINITY;
    for v in v0..=v1 + 1 {
        for u in u0..=u1 + 1 {
            let (_, _, raw) = block_vertex(hf, layout, b, u as u32, v as u32);
            top = top.max((raw * hf.height_scale) as f64);
        }
    }
    top
}

/// One drawn block as the sweep tests it.
struct Query {
    rect: Rect,
    near: f64,
    far: f64,
    hi: f64,
}

/// A cell of a drawn block's footprint under its lowest drawn height.
struct Occluder {
    /// Clipped to the true extent (nothing beyond it is shown).
    rect: Rect,
    near: f64,
    far: f64,
    lo: f64,
}

/// The occluder cells of drawn block `b`: its footprint in 4 x 4 cells of the min/max
/// pyramid (or cells one parent quad wide, for blocks of fewer quads), each under its
/// lowest sample. Over an interior cell the drawn surface is the cell's own quads, morphed
/// towards the parent's triangles, whose vertices are the cell's samples (the cells are
/// aligned to the parent's grid); over a cell along an edge stitched to a coarser block
/// the fan triangles reach further along the edge, so the cell takes the block's whole
/// drawn minimum there.
fn cells<'a>(
    hf: &'a Heightfield,
    mm: &'a MinMaxPyramid,
    layout: &BlockLayout,
    b: &'a DrawBlock,
    block_lo: f32,
) -> impl Iterator<Item = (Rect, f64)> + 'a {
    let level = (layout.m + b.lod).saturating_sub(2).max(b.lod + 1).min(layout.m + b.lod);
    let per_side = 1u32 << (layout.m + b.lod - level);
    let size = (1u64 << level) as f64;
    let hs = hf.height_scale;
    (0..per_side * per_side).map(move |g| {
        let (gx, gz) = (g % per_side, g / per_side);
        let (x, z) = (b.bx * per_side + gx, b.bz * per_side + gz);
        let (x0, z0) = (x as f64 * size * hf.spacing.x as f64, z as f64 * size * hf.spacing.z as f64);
        let rect = Rect { x0, z0, x1: x0 + size * hf.spacing.x as f64, z1: z0 + size * hf.spacing.z as f64 };
        let mut lo = mm.get(level, x as usize, z as usize)[0] * hs;
        let on_edge = [gz == 0, gx == per_side - 1, gz == per_side - 1, gx == 0];
        if (0..4).any(|e| on_edge[e] && b.coarser[e] > 0) {
            lo = lo.min(block_lo);
        }
        (rect, lo as f64)
    })
}

/// A part's box as the sweep tests it ([`SweptBlock::parts`]): its square of samples
/// `(x0, z0, size)` with spacing `(sx, sz)` from sample `origin`, and its raw heights
/// scaled by `hs`.
pub fn part_of(pb: &crate::lod::block::PartBox, origin: [i64; 2], (sx, sz): (f64, f64), hs: f64) -> SweptPart {
    let (x0, z0) = ((pb.x0 - origin[0]) as f64 * sx, (pb.z0 - origin[1]) as f64 * sz);
    let size = pb.size as f64;
    let rect = Rect { x0, z0, x1: x0 + size * sx, z1: z0 + size * sz };
    SweptPart { rect, range: [pb.raw[0] as f64 * hs, pb.raw[1] as f64 * hs], bit: pb.bit }
}

/// Moves the blocks of `t` that no pixel can see into `t.occluded` (keeping their
/// neighbours' stitching as it was), marks the hidden parts of the others
/// (`DrawBlock::hidden_parts`, which the renderer leaves out), and says what it did.
pub fn cull(
    hf: &Heightfield,
    mm: &MinMaxPyramid,
    caches: &BlockCaches,
    layout: &BlockLayout,
    cam: &Camera,
    t: &mut Traversal,
) -> OcclusionReport {
    let hidden = hidden_parts(hf, mm, caches, layout, cam, t);
    let per_block = layout.parts_per_side().pow(2) as usize;
    let mut report = OcclusionReport {
        tested: t.blocks.len(),
        tested_parts: t.blocks.len() * per_block,
        skipped: hidden.as_ref().err().copied(),
        ..Default::default()
    };
    let Ok(hidden) = hidden else {
        t.occlusion = Some(report);
        return report;
    };
    let all = layout.all_parts();
    report.hidden = hidden.iter().filter(|&&h| h == all).count();
    report.hidden_parts = hidden.iter().map(|h| h.count_ones() as usize).sum();
    t.occlusion = Some(report);
    if report.hidden_parts > 0 {
        let blocks = std::mem::take(&mut t.blocks);
        let errors = std::mem::take(&mut t.selection_errors);
        for ((b, e), &h) in blocks.into_iter().zip(errors).zip(&hidden) {
            if h == all {
                t.occluded.push(b);
            } else {
                t.blocks.push(DrawBlock { hidden_parts: h, ..b });
                t.selection_errors.push(e);
            }
        }
    }
    report
}

/// The rule the sweep applies: the sound one, or one broken on purpose so that the
/// culling tests can show they catch it (mutation tests).
#[doc(hidden)]
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Rule {
    Sound,
    /// Occluders at their block's highest drawn height instead of its lowest.
    OccluderTop,
    /// Every block tested against every occluder, nearer or not (no sweep order).
    Unordered,
    /// Parts tested at their lowest sample instead of their highest.
    PartBottom,
}

/// Per block of `t.blocks`, its hidden parts (`DrawBlock::hidden_parts`'s bits;
/// `layout.all_parts()`: the whole block is hidden); or why the frame cannot be culled.
pub fn hidden_parts(
    hf: &Heightfield,
    mm: &MinMaxPyramid,
    caches: &BlockCaches,
    layout: &BlockLayout,
    cam: &Camera,
    t: &Traversal,
) -> Result<Vec<u16>, Skipped> {
    hidden_parts_with(hf, mm, caches, layout, cam, t, Rule::Sound)
}

#[doc(hidden)]
pub fn hidden_parts_with(
    hf: &Heightfield,
    mm: &MinMaxPyramid,
    caches: &BlockCaches,
    layout: &BlockLayout,
    cam: &Camera,
    t: &Traversal,
    rule: Rule,
) -> Result<Vec<u16>, Skipped> {
    if hf.void_mask.is_some() {
        return Err(Skipped::Holes);
    }
    let [cells_x, rows] = layout.cells().map(|c| c as i64);
    let coarse_beside = |k: &DrawBlock| {
        k.cells_across().into_iter().any(|(x, z)| {
            let lod =
                if x < 0 || z < 0 || x >= cells_x || z >= rows { -1 } else { t.lod_map[(z * cells_x + x) as usize] };
            lod >= 0 && lod as u32 >= k.lod + layout.m
        })
    };
    if t.frustum_culled.iter().any(coarse_beside) {
        return Err(Skipped::CoarseBesideCulled);
    }
    let (ex, ez) = hf.world_extent();
    let extent = Rect { x0: 0.0, z0: 0.0, x1: ex as f64, z1: ez as f64 };
    let [sx, sz] = [hf.spacing.x as f64, hf.spacing.z as f64];
    let hs = hf.height_scale as f64;
    let blocks: Vec<SweptBlock> = t
        .blocks
        .iter()
        .map(|b| {
            let s = layout.block_samples(b.lod) as f64;
            let (ox, oz) = (b.bx as f64 * s, b.bz as f64 * s);
            let rect = Rect { x0: ox * sx, z0: oz * sz, x1: (ox + s) * sx, z1: (oz + s) * sz };
            let [lo, hi] = drawn_range(hf, mm, caches, layout, b);
            SweptBlock {
                rect,
                range: [lo as f64, hi as f64],
                cells: cells(hf, mm, layout, b, lo).collect(),
                parts: part_boxes(mm, layout, b).map(|pb| part_of(&pb, [0, 0], (sx, sz), hs)).collect(),
            }
        })
        .collect();
    // A frustum-culled block's box is outside the frustum, so the near plane over it is
    // above its highest sample or below its lowest.
    let culled: Vec<(Rect, f64)> = t
        .frustum_culled
        .iter()
        .map(|k| block_aabb(hf, mm, layout, k.lod, k.bx, k.bz))
        .map(|(min, max)| {
            (Rect { x0: min.x as f64, z0: min.z as f64, x1: max.x as f64, z1: max.z as f64 }, min.y as f64)
        })
        .collect();
    let top_over = |i: usize, area: &Rect| top_over(hf, layout, &t.blocks[i], area, blocks[i].range[1]);
    let frame =
        SweptFrame { extent, blocks: &blocks, culled: &culled, all_parts: layout.all_parts(), top_over: &top_over };
    sweep(cam, &frame, rule)
}

/// One drawn block as the sweep sees it, whatever holds its heights: world units, in the
/// frame the camera's position is given in.
#[derive(Clone, Debug)]
pub struct SweptBlock {
    /// Its footprint, and the lowest and highest points of everything drawn over it.
    pub rect: Rect,
    pub range: [f64; 2],
    /// Cells of its footprint, each with a height the drawn surface over it never dips
    /// under (the occluders).
    pub cells: Vec<(Rect, f64)>,
    /// Its parts that can be left out alone.
    pub parts: Vec<SweptPart>,
}

/// A part of a drawn block: its footprint, the lowest and highest of its triangles'
/// vertices, and its bit of [`DrawBlock::hidden_parts`].
#[derive(Clone, Copy, Debug)]
pub struct SweptPart {
    pub rect: Rect,
    pub range: [f64; 2],
    pub bit: u16,
}

/// A frame as the sweep sees it.
pub struct SweptFrame<'a> {
    /// The terrain's true extent (nothing beyond it is shown).
    pub extent: Rect,
    pub blocks: &'a [SweptBlock],
    /// The frustum-culled blocks: footprint and lowest sample.
    pub culled: &'a [(Rect, f64)],
    /// Every bit of a block's parts ([`BlockLayout::all_parts`]): the whole block.
    pub all_parts: u16,
    /// The highest drawn point of block `i` over an area its footprint meets (its whole
    /// range's top where nothing finer is known).
    pub top_over: &'a dyn Fn(usize, &Rect) -> f64,
}

/// Per block of `frame`, its hidden parts (bits of `DrawBlock::hidden_parts`; every bit
/// of the block's own parts: the whole block is hidden), by `rule`; or why the frame
/// cannot be culled (the camera off the extent, or the near plane at the ground).
pub fn sweep(cam: &Camera, frame: &SweptFrame, rule: Rule) -> Result<Vec<u16>, Skipped> {
    let extent = frame.extent;
    let c = cam.position.as_dvec3();
    if !(c.x > extent.x0 && c.x < extent.x1 && c.z > extent.z0 && c.z < extent.z1) {
        return Err(Skipped::CameraOutside);
    }
    let clip = |r: &Rect| {
        let r =
            Rect { x0: r.x0.max(extent.x0), z0: r.z0.max(extent.z0), x1: r.x1.min(extent.x1), z1: r.z1.min(extent.z1) };
        (r.x1 > r.x0 && r.z1 > r.z0).then_some(r)
    };
    let mut occ = Vec::with_capacity(frame.blocks.len() * 16);
    // Each block's whole box, then its parts' boxes; `owners` says whose each is and the
    // bits of `hidden_parts` it hides.
    let mut parts = Vec::with_capacity(frame.blocks.len() * 16);
    let mut queries = Vec::with_capacity(frame.blocks.len() * 17);
    let mut owners = Vec::with_capacity(frame.blocks.len() * 17);
    for (i, b) in frame.blocks.iter().enumerate() {
        let (near, far) = b.rect.distances(c.x, c.z);
        let occluder = |(r, lo): (Rect, f64)| {
            let (near, far) = r.distances(c.x, c.z);
            Occluder { rect: r, near, far, lo }
        };
        if rule == Rule::OccluderTop {
            occ.extend(clip(&b.rect).map(|r| occluder((r, b.range[1]))));
        } else {
            occ.extend(b.cells.iter().filter_map(|(r, lo)| clip(r).map(|r| occluder((r, *lo)))));
        }
        let top = if rule == Rule::PartBottom { 0 } else { 1 };
        parts.extend(b.parts.iter().map(|p| {
            let (near, far) = p.rect.distances(c.x, c.z);
            (Query { rect: p.rect, near, far, hi: p.range[top] }, i, p.bit)
        }));
        queries.push(Query { rect: b.rect, near, far, hi: b.range[1] });
        owners.push((i, frame.all_parts));
    }
    owners.extend(parts.iter().map(|p| (p.1, p.2)));
    queries.extend(parts.into_iter().map(|p| p.0));

    // The near plane's corners, and how far from the camera they reach across the ground.
    let (right, up) = cam.basis();
    let (tv, th) = ((cam.fovy as f64 * 0.5).tan(), (cam.fovy as f64 * 0.5).tan() * cam.aspect() as f64);
    let (f, right, up, near) = (cam.forward.as_dvec3(), right.as_dvec3(), up.as_dvec3(), cam.near as f64);
    let corners = [(-1.0, -1.0), (1.0, -1.0), (1.0, 1.0), (-1.0, 1.0)]
        .map(|(u, v): (f64, f64)| c + near * (f + right * (u * th) + up * (v * tv)));
    let reach = corners.iter().map(|p| (p.x - c.x).hypot(p.z - c.z)).fold(0.0, f64::max);
    let near_low = corners.iter().map(|p| p.y).fold(f64::INFINITY, f64::min);
    let near_box = Rect { x0: c.x - reach, z0: c.z - reach, x1: c.x + reach, z1: c.z + reach };
    let touches = |r: &Rect| r.x0 <= near_box.x1 && r.x1 >= near_box.x0 && r.z0 <= near_box.z1 && r.z1 >= near_box.z0;
    let drawn_top = (0..frame.blocks.len())
        .filter(|&i| touches(&frame.blocks[i].rect))
        .map(|i| (frame.top_over)(i, &near_box))
        .fold(f64::NEG_INFINITY, f64::max);
    // A frustum-culled block's box is outside the frustum, so the near plane over it is
    // above its highest sample or below its lowest: above its lowest rules out the latter.
    let culled_low =
        frame.culled.iter().filter(|(r, _)| touches(r)).map(|&(_, low)| low).fold(f64::NEG_INFINITY, f64::max);
    let under_near = drawn_top.max(culled_low);
    if under_near >= near_low {
        return Err(Skipped::NearPlaneLow);
    }

    // Two pixels of angle: a pixel subtends at most 1 / kappa radians.
    let margin = 2.0 / cam.kappa() as f64;
    let width = TAU / BINS as f64;
    // Sweep outward: an occluder joins at its farthest distance, a block is tested at its
    // nearest, so it meets only occluders it lies wholly beyond (occluders first on ties).
    let mut events: Vec<(f64, bool, usize)> = Vec::with_capacity(queries.len() + occ.len());
    for (i, o) in occ.iter().enumerate() {
        if o.near > reach {
            events.push((if rule == Rule::Unordered { 0.0 } else { o.far }, false, i));
        }
    }
    for (i, q) in queries.iter().enumerate() {
        if q.near > reach {
            events.push((q.near, true, i));
        }
    }
    events.sort_by(|a, b| a.0.total_cmp(&b.0).then(a.1.cmp(&b.1)));
    // Per bin, the tangent of the elevation below which every ray dips under an occluder.
    let mut horizon = vec![f64::NEG_INFINITY; BINS];
    let edges = bin_edges();
    let edge = |k: i64| edges[k.rem_euclid(BINS as i64) as usize];
    let mut hidden = vec![false; queries.len()];
    for (_, query, i) in events {
        if query {
            let q = &queries[i];
            let (a, b) = q.rect.azimuths(c.x, c.z);
            // The highest elevation anywhere in the box, raised by the margin.
            let top = if q.hi >= c.y { (q.hi - c.y) / q.near } else { (q.hi - c.y) / q.far };
            let top = top.atan() + margin;
            if top >= std::f64::consts::FRAC_PI_2 {
                continue;
            }
            let top = top.tan();
            let (first, last) = (((a - margin) / width).floor() as i64, ((b + margin) / width).floor() as i64);
            hidden[i] = (first..=last).all(|k| top < horizon[k.rem_euclid(BINS as i64) as usize]);
        } else {
            let o = &occ[i];
            let (a, b) = o.rect.azimuths(c.x, c.z);
            let (first, last) = ((a / width).ceil() as i64, (b / width).floor() as i64);
            if last <= first {
                continue;
            }
            let mut prev = o.rect.exit(c.x, c.z, edge(first));
            for k in first..last {
                let next = o.rect.exit(c.x, c.z, edge(k + 1));
                // Every ray of the bin is under `lo` somewhere before it leaves the cell
                // when the tangent of its elevation is below this.
                let e = if o.lo < c.y { (o.lo - c.y) / nearest_exit(prev, next) } else { (o.lo - c.y) / o.far };
                prev = next;
                let bin = &mut horizon[k.rem_euclid(BINS as i64) as usize];
                *bin = bin.max(e);
            }
        }
    }
    let mut masks = vec![0u16; frame.blocks.len()];
    assert_eq!(owners.len(), hidden.len(), "one owner per query");
    for (&(block, bits), _) in owners.iter().zip(&hidden).filter(|(_, &h)| h) {
        masks[block] |= bits;
    }
    Ok(masks)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A small deterministic generator.
    fn rng(state: &mut u64) -> f64 {
        *state = state.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
        (*state >> 11) as f64 / (1u64 << 53) as f64
    }

    fn random_case(s: &mut u64) -> (Rect, f64, f64) {
        let (x0, z0) = (rng(s) * 100.0 - 50.0, rng(s) * 100.0 - 50.0);
        let r = Rect { x0, z0, x1: x0 + 0.5 + rng(s) * 40.0, z1: z0 + 0.5 + rng(s) * 40.0 };
        loop {
            let (cx, cz) = (rng(s) * 200.0 - 100.0, rng(s) * 200.0 - 100.0);
            if !r.contains(cx, cz) {
                return (r, cx, cz);
            }
        }
    }

    /// A run that does not pay (here: the camera is off the terrain, so nothing can be
    /// proven hidden) pauses the sweep for `EVERY - 1` frames, then it runs again.
    #[test]
    fn an_unpaying_sweep_pauses_then_tries_again() {
        use crate::lod::traversal::{traverse, LodSelect};
        let samples: Vec<f32> = (0..129 * 129).map(|i| ((i % 129) as f32 * 0.2).sin() * 5.0).collect();
        let hf =
            Heightfield::embed("waves", 129, 129, &samples, crate::lod::heightfield::HeightFormat::Float32, 1.0, 1.0)
                .unwrap();
        let mm = MinMaxPyramid::build(&hf);
        let layout = BlockLayout::of(&hf, 9).unwrap();
        let caches = BlockCaches::default();
        let (wx, wz) = hf.world_extent();
        let cam = Camera::look_at(
            glam::Vec3::new(wx * 0.5, wx * 0.2, wz * 1.2),
            glam::Vec3::new(wx * 0.5, 0.0, wz * 0.5),
            60.0,
            320,
            240,
            crate::lod::view::near_plane(&hf),
        );
        let mut probe = Probe::default();
        let mut seen = Vec::new();
        for _ in 0..(2 * Probe::EVERY + 1) {
            let mut t = traverse(&hf, &mm, &caches, &layout, &cam, LodSelect::Distance { factor: 2.0 });
            seen.push(probe.cull(&hf, &mm, &caches, &layout, &cam, &mut t).skipped);
            assert_eq!(t.occlusion.map(|o| o.skipped), Some(*seen.last().unwrap()));
        }
        let ran: Vec<usize> = (0..seen.len()).filter(|&i| seen[i] != Some(Skipped::Paused)).collect();
        assert_eq!(ran, [0, Probe::EVERY as usize, 2 * Probe::EVERY as usize], "{seen:?}");
        assert!(ran.iter().all(|&i| seen[i] == Some(Skipped::CameraOutside)));
    }

    /// A sweep pays when the triangles it hid would have cost the GPU at least its own
    /// time, whatever share of the parts that is; a skipped one never pays; untimed, the
    /// share decides.
    #[test]
    fn a_sweep_pays_by_the_time_it_saves() {
        let r = |hidden_parts, tested_parts| OcclusionReport { hidden_parts, tested_parts, ..Default::default() };
        // 100 parts of 128 triangles at 100 ns: 1.28 ms saved.
        assert!(Probe::pays(&r(100, 20_000), 1.2, Some(100.0), 128));
        assert!(!Probe::pays(&r(100, 20_000), 1.3, Some(100.0), 128));
        // The same sweep at 2 ns a triangle saves 0.0256 ms: it does not pay, though it
        // hid more than PAYS of the parts.
        assert!(!Probe::pays(&r(300, 20_000), 0.5, Some(2.0), 128));
        assert!(Probe::pays(&r(300, 20_000), 0.5, None, 128));
        assert!(!Probe::pays(&r(100, 20_000), 0.5, None, 128));
        let skipped = OcclusionReport { skipped: Some(Skipped::CameraOutside), ..r(20_000, 20_000) };
        assert!(!Probe::pays(&skipped, 0.0, Some(100.0), 128));
        // What a frame's timing teaches: 2 ms for a million triangles is 2 ns each.
        let mut p = Probe::default();
        p.observe(None, 1_000_000);
        assert_eq!(p.timing, None);
        p.observe(Some(2.0), 0);
        assert_eq!(p.timing, None);
        p.observe(Some(2.0), 1_000_000);
        assert_eq!(p.timing, Some((2.0, 2.0)));
    }

    /// Sweeps that do not pay take at most SHARE of the frames' time: a 16 ms sweep
    /// beside 3.5 ms frames (a GPU) pauses 92 frames; beside 200 ms frames (lavapipe) the
    /// least pause; untimed, the least pause; never longer than MAX_PAUSE.
    #[test]
    fn sweeps_that_do_not_pay_take_a_bounded_share_of_the_time() {
        let pause = Probe::pause_after(16.0, Some(3.5));
        assert_eq!(pause, 92);
        assert!(16.0 / (pause as f64 * 3.5) <= Probe::SHARE);
        assert_eq!(Probe::pause_after(12.0, Some(200.0)), Probe::EVERY);
        assert_eq!(Probe::pause_after(16.0, None), Probe::EVERY);
        assert_eq!(Probe::pause_after(1e6, Some(0.1)), Probe::MAX_PAUSE);
    }

    /// The interval holds every point of the rectangle, and no wider than its corners.
    #[test]
    fn azimuths_cover_the_rectangle() {
        let mut s = 7u64;
        for _ in 0..2000 {
            let (r, cx, cz) = random_case(&mut s);
            let (a, b) = r.azimuths(cx, cz);
            assert!((0.0..TAU).contains(&a) && b > a && b - a < std::f64::consts::PI);
            for _ in 0..50 {
                let (x, z) = (r.x0 + rng(&mut s) * (r.x1 - r.x0), r.z0 + rng(&mut s) * (r.z1 - r.z0));
                let phi = (z - cz).atan2(x - cx).rem_euclid(TAU);
                let inside = |p: f64| p >= a - 1e-12 && p <= b + 1e-12;
                assert!(inside(phi) || inside(phi + TAU), "{r:?} from ({cx}, {cz}): {phi} outside [{a}, {b}]");
            }
        }
    }

    /// Over a bin inside the interval, no ray leaves the rectangle nearer than the
    /// nearest exit taken from the bin's edges, and one leaves about there (sampled
    /// densely; the bound is tight).
    #[test]
    fn nearest_exit_is_the_least_exit_over_the_bin() {
        let mut s = 11u64;
        let (edges, width) = (bin_edges(), TAU / BINS as f64);
        let mut checked = 0;
        while checked < 3000 {
            let (r, cx, cz) = random_case(&mut s);
            let (a, b) = r.azimuths(cx, cz);
            let (first, last) = ((a / width).ceil() as i64, (b / width).floor() as i64);
            if last <= first {
                continue;
            }
            let k = first + ((last - first) as f64 * rng(&mut s)) as i64;
            let e = |k: i64| edges[k.rem_euclid(BINS as i64) as usize];
            let bound = nearest_exit(r.exit(cx, cz, e(k)), r.exit(cx, cz, e(k + 1)));
            let mut least = f64::INFINITY;
            for i in 0..=400 {
                let phi = (k as f64 + i as f64 / 400.0) * width;
                let d = r.exit(cx, cz, (phi.cos(), phi.sin()));
                assert!(d >= bound * (1.0 - 1e-9), "{r:?} from ({cx}, {cz}) at {phi}: exit {d} < bound {bound}");
                least = least.min(d);
            }
            assert!(least <= bound * (1.0 + 1e-6), "bound {bound} below the least sampled exit {least}");
            checked += 1;
        }
    }
}
