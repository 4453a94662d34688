//! Geomorphing inside the bound (SPEC section 3: "anything that changes the drawn surface
//! adds its own term"). A block's odd vertices move from its parent's surface (factor 0)
//! to their own samples (factor 1); a block that has just split starts on its parent's
//! surface, and one about to split is on its own, so its surface does not jump.
//!
//! Which vertices morph, so that the surface stays watertight (`EdgeVars`):
//! - interior vertices, with the block's factor `f`;
//! - vertices on an edge shared with a block of the same LOD, with one factor for the
//!   edge (no other block touches them);
//! - the odd vertices of a block's edge next to finer blocks, with one factor for the
//!   edge, which those blocks are given too: their collapsed edge vertices follow the
//!   morphed edge, so a block next to a coarser one moves with it instead of jumping
//!   when that block splits or merges;
//! - not corners: a corner of a finer block always lands on an even (unmorphed) vertex of
//!   a coarser edge when the LODs differ by less than `m` (`k = 2^m + 1`); edges between
//!   LODs further apart stay fixed.
//!
//! The factor is chosen per frame, as small as the bound allows. At every sample the
//! drawn surface is an affine function of the factors of the vertex groups around it
//! (the triangulation does not move), so its deviation is convex in them and at most the
//! multilinear interpolation of its values at the extreme states, which are measured
//! exactly:
//! - interior quads (one group, `f`): `(1 - f) E0 + f E1`, per parent group with that
//!   group's distance, as the errors activity does: `E0` from `D_{j+1}`, `E1` from the
//!   largest `D_j` of the group's four children;
//! - the strip along each edge (`f` and the edge's factor) and each corner quad (`f` and
//!   the two edges' factors): exact deviations in every state (`stitch::EdgeRegions`,
//!   cached per block and neighbours).
//!
//! At the moment a block splits its parent's error is delta, so `E0 <= delta` and `f = 0`
//! fits unless an edge region does not. The factors start from a ramp and only rise: a
//! block over the bound raises its factor and its edges together to the least value (in
//! steps of 1/64) that meets it, until nothing changes; factor 1 with every edge at 1 is the selection's own surface,
//! which the selection already bounds, so it always ends.
//!
//! Pixels per world unit of a group: `kappa * a_b / dist(group box)`, with `a_b` the
//! block's angular factor ([`crate::lod::camera::angular_factor`]); the edge regions use the
//! block's box grown to every state's heights. Computed fresh for this frame's camera, so
//! stale error data plays no part here.

use crate::lod::block::{block_aabb, map_in_pool, morph_value, BlockLayout, DrawBlock, Traversal, MORPH_ONE};
use crate::lod::block_cache::BoundedCache;
use crate::lod::camera::angular_factor;
use crate::lod::camera::{distance_to_aabb, Camera};
use crate::lod::heightfield::Heightfield;
use crate::lod::pyramid::MinMaxPyramid;
use crate::lod::stitch::{strip_segment, StitchCache, CORNER_EDGES, STRIP_SEGMENTS};
use foldhash::HashMap;

/// What a block's morph costs, in pixels for this frame's camera.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct MorphCost {
    /// Bound on the error of the interior quads, every vertex at factor 0.
    pub parent: f32,
    /// The same with every vertex at factor 1.
    pub own: f32,
    /// Edge strips and corner quads in each state ([`crate::lod::stitch::EdgeRegions`]).
    pub side: [[f32; 4]; 4],
    pub corner: [[f32; 8]; 4],
}

fn lerp(a: f32, b: f32, t: f32) -> f32 {
    a + (b - a) * t
}

impl MorphCost {
    /// The tighter of two bounds in each extreme state (both bound the same surface, so
    /// their minimum does; the interpolation between states stays an upper bound).
    pub fn min(&self, o: &MorphCost) -> MorphCost {
        let m = |a: f32, b: f32| a.min(b);
        MorphCost {
            parent: m(self.parent, o.parent),
            own: m(self.own, o.own),
            side: std::array::from_fn(|s| std::array::from_fn(|t| m(self.side[s][t], o.side[s][t]))),
            corner: std::array::from_fn(|c| std::array::from_fn(|t| m(self.corner[c][t], o.corner[c][t]))),
        }
    }

    /// Bound on the block's error with interior factor `f` and edge factors `e` (fixed
    /// edges' regions do not depend on theirs). The deviation at a sample is the absolute value of an
    /// affine function of the factors, so over each region it is at most the
    /// multilinear interpolation of its values at the extreme states.
    pub fn bound(&self, f: f32, e: [f32; 4]) -> f32 {
        let mut m = lerp(self.parent, self.own, f);
        for (s, d) in self.side.iter().enumerate() {
            m = m.max(lerp(lerp(d[0], d[1], e[s]), lerp(d[2], d[3], e[s]), f));
        }
        for (c, d) in self.corner.iter().enumerate() {
            let [a, b] = CORNER_EDGES[c];
            let at = |fs: usize| lerp(lerp(d[fs], d[fs + 1], e[b]), lerp(d[fs + 2], d[fs + 3], e[b]), e[a]);
            m = m.max(lerp(at(0), at(4), f));
        }
        m
    }
}

/// How factors are chosen: the renderer's rule, or rules broken on purpose for the
/// mutation tests (the audit must catch them).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum MorphRule {
    /// Everything above.
    Bounded,
    /// Half of each factor the bound asks for: the morph underpaid.
    Underpaid,
    /// Every block on its parent's surface (factor 0), the bound ignored.
    ParentSurface,
    /// [`MorphRule::Bounded`] with each exact term computed only where the rounds ask for
    /// it, on the calling thread: what the renderer's rule must equal (a test).
    BoundedLazy,
}

/// How the edge regions are measured.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum EdgeTerms {
    /// Sample by sample in every state ([`crate::lod::stitch::edge_regions`], cached).
    Exact,
    /// From the vertices' moves ([`crate::lod::stitch::edge_regions_bound`], cached): looser,
    /// `O(k)`.
    Cheap,
}

/// The morph's cost for block `b` (with its neighbours' strides set) whose edges in
/// `fixed` do not morph.
#[allow(clippy::too_many_arguments)]
pub fn cost(
    hf: &Heightfield,
    mm: &MinMaxPyramid,
    caches: &BlockCaches,
    layout: &BlockLayout,
    cam: &Camera,
    delta: f32,
    b: &DrawBlock,
    fixed: u8,
    terms: EdgeTerms,
) -> MorphCost {
    let hs = hf.height_scale;
    let j = b.lod;
    let regions = match terms {
        EdgeTerms::Exact => caches.stitch.regions(hf, mm, layout, b, fixed),
        EdgeTerms::Cheap => caches.stitch.regions_bound(hf, mm, layout, b, fixed),
    };
    let (mut min, mut max) = block_aabb(hf, mm, layout, j, b.bx, b.bz);
    min.y = min.y.min(regions.lo * hs);
    max.y = max.y.max(regions.hi * hs);
    let per_group = cam.kappa() * angular_factor(cam, min, max, delta);
    // Each edge region projected from its own box (the block's heights, the region's
    // extent in x and z) with the block's angular factor, as the interior groups are:
    // the far part of a block is much farther than its nearest point.
    let (ox, oz) = b.origin(layout);
    let (size, st) = (layout.block_samples(j), b.stride());
    let last = layout.k() - 2; // last quad index
    let px = |[x0, z0, x1, z1]: [u32; 4]| {
        let (lo, hi) = hf.world_box(x0 as i64, z0 as i64, x1 as i64, z1 as i64, [min.y, max.y]);
        per_group * hs / distance_to_aabb(cam.position, lo, hi).max(cam.near)
    };
    // A stitched strip's triangles fan out from the coarser edge's vertices, which lie
    // up to that edge's stride along it: a quad's triangles cover samples that many quads
    // beyond it, in the next segment or corner (an adversarial review's field audited 1.47
    // px against a bound of 0.995 with the quads' own boxes).
    let reach = |e: usize| b.coarser[e] / st;
    // Box of quads `t0..=t1` along edge `e` and the samples their triangles reach, in
    // samples `[x0, z0, x1, z1]`.
    let strip_box = |e: usize, t0: u32, t1: u32| -> [u32; 4] {
        let (t0, t1) = (t0.saturating_sub(reach(e)), (t1 + reach(e)).min(last));
        let (a, b) = (t0 * st, (t1 + 1) * st);
        match e {
            0 => [ox + a, oz, ox + b, oz + st],
            1 => [ox + size - st, oz + a, ox + size, oz + b],
            2 => [ox + a, oz + size - st, ox + b, oz + size],
            _ => [ox, oz + a, ox + st, oz + b],
        }
    };
    // The first and last quad of each segment (the same along every edge).
    let mut range: [Option<(u32, u32)>; STRIP_SEGMENTS] = [None; STRIP_SEGMENTS];
    for t in 1..last {
        let r = &mut range[strip_segment(t, last)];
        *r = Some(r.map_or((t, t), |(t0, _)| (t0, t)));
    }
    let mut sides = [[0.0f32; 4]; 4];
    for (e, segments) in regions.side.iter().enumerate() {
        for (d, r) in segments.iter().zip(range) {
            let Some((t0, t1)) = r else { continue };
            let f = px(strip_box(e, t0, t1));
            for (m, v) in sides[e].iter_mut().zip(d) {
                *m = m.max(v * f);
            }
        }
    }
    let corner_quads = [(0, 0), (last, 0), (last, last), (0, last)];
    let corner: [[f32; 8]; 4] = std::array::from_fn(|c| {
        let (u, v) = corner_quads[c];
        // Edges 0 and 2 run along x, 1 and 3 along z.
        let [ea, eb] = CORNER_EDGES[c];
        let (rx, rz) = (reach(ea), reach(eb));
        let (u0, u1) = (u.saturating_sub(rx), (u + rx).min(last));
        let (v0, v1) = (v.saturating_sub(rz), (v + rz).min(last));
        let f = px([ox + u0 * st, oz + v0 * st, ox + (u1 + 1) * st, oz + (v1 + 1) * st]);
        regions.corner[c].map(|d| d * f)
    });

    let (parent, own) = interior(hf, mm, caches, layout, cam, b, per_group);
    MorphCost { parent, own, side: sides, corner }
}

/// Tiles a side in [`InteriorTiles`].
const TILES: usize = 4;

/// The per-block results the traversal keeps between frames: the stitched strips and
/// edge regions ([`StitchCache`]) and the interiors' tile summaries. None depends on the
/// camera, so a block keeps its entries while it stays drawn. Owned by whoever traverses
/// (the draw thread, the quality sweep, a test), not by the terrain.
#[derive(Clone, Debug, Default)]
pub struct BlockCaches {
    pub stitch: StitchCache,
    pub interiors: BoundedCache<(u32, u32, u32, u32), InteriorTiles>,
}

/// A block's interior parent groups (level `j + 1`) in `TILES x TILES` tiles, without a
/// camera: per tile its groups `[gx0, gz0, gx1, gz1)`, their raw height range and their
/// largest `E0` and `E1` deviations (raw units). A group is no nearer the camera than its
/// tile's box, so a tile's deviations over that box's distance bound every group's term,
/// and a tile whose bound cannot raise the maximum found so far is skipped.
#[derive(Clone, Copy, Debug, Default)]
pub struct InteriorTiles {
    groups: [[u32; 4]; TILES * TILES],
    /// `[lo, hi, E0, E1]`.
    values: [[f32; 4]; TILES * TILES],
}

/// The `E0` and `E1` deviations (raw units) of parent group `(gx, gz)` of a LOD-`j` block.
fn group_deviations(mm: &MinMaxPyramid, j: u32, gx: usize, gz: usize) -> (f32, f32) {
    let d0 = mm.deviation(j + 1, gx, gz);
    let dc = if j == 0 {
        0.0
    } else {
        let mut m = 0.0f32;
        for (cx, cz) in [(0, 0), (1, 0), (0, 1), (1, 1)] {
            m = m.max(mm.deviation(j, 2 * gx + cx, 2 * gz + cz));
        }
        m
    };
    (d0, dc)
}

/// The block's parent groups (level `j + 1`) `[gx0, gz0, gx1, gz1)`, clipped to the grid.
fn interior_groups(mm: &MinMaxPyramid, layout: &BlockLayout, b: &DrawBlock) -> [usize; 4] {
    let gs = 1usize << (b.lod + 1);
    let per_side = (layout.k() as usize - 1) / 2;
    let (ox, oz) = b.origin(layout);
    let (ga, gb) = (ox as usize / gs, oz as usize / gs);
    let [cells, rows] = mm.cells(b.lod + 1);
    [ga, gb, (ga + per_side).min(cells), (gb + per_side).min(rows)]
}

impl InteriorTiles {
    fn new(mm: &MinMaxPyramid, layout: &BlockLayout, b: &DrawBlock) -> Self {
        let [ga, gb, ge, gf] = interior_groups(mm, layout, b);
        let per_side = (layout.k() as usize - 1) / 2;
        let step = per_side.div_ceil(TILES);
        let mut out = InteriorTiles::default();
        for ty in 0..TILES {
            for tx in 0..TILES {
                let (x0, z0) = ((ga + tx * step).min(ge), (gb + ty * step).min(gf));
                let (x1, z1) = ((x0 + step).min(ge), (z0 + step).min(gf));
                let mut v = [f32::INFINITY, f32::NEG_INFINITY, 0.0, 0.0];
                for gz in z0..z1 {
                    for gx in x0..x1 {
                        let (d0, dc) = group_deviations(mm, b.lod, gx, gz);
                        let [lo, hi] = mm.get(b.lod + 1, gx, gz);
                        v = [v[0].min(lo), v[1].max(hi), v[2].max(d0), v[3].max(dc)];
                    }
                }
                out.groups[ty * TILES + tx] = [x0, z0, x1, z1].map(|g| g as u32);
                out.values[ty * TILES + tx] = v;
            }
        }
        out
    }
}

/// The interior's bound with every vertex at factor 0 (`parent`) and at factor 1 (`own`),
/// in pixels: per parent group (level `j + 1`), as the errors activity projects, its
/// deviation over its box's distance. Exactly the maximum over all groups; tiles that
/// cannot raise it are skipped ([`InteriorTiles`]).
fn interior(
    hf: &Heightfield,
    mm: &MinMaxPyramid,
    caches: &BlockCaches,
    layout: &BlockLayout,
    cam: &Camera,
    b: &DrawBlock,
    per_group: f32,
) -> (f32, f32) {
    let tiles = caches.interiors.get_or_compute((layout.m, b.lod, b.bx, b.bz), || InteriorTiles::new(mm, layout, b));
    let hs = hf.height_scale;
    let group = 1i64 << (b.lod + 1);
    let scale = |[x0, z0, x1, z1]: [u32; 4], lo: f32, hi: f32| {
        let g = |v: u32| v as i64 * group;
        let (gmin, gmax) = hf.world_box(g(x0), g(z0), g(x1), g(z1), [lo * hs, hi * hs]);
        per_group / distance_to_aabb(cam.position, gmin, gmax).max(cam.near)
    };
    let mut order: [(f32, usize); TILES * TILES] = std::array::from_fn(|t| {
        let [lo, hi, d0, dc] = tiles.values[t];
        let f = if d0 == 0.0 && dc == 0.0 { 0.0 } else { scale(tiles.groups[t], lo, hi) };
        (f, t)
    });
    let reach = |&(f, t): &(f32, usize)| tiles.values[t][2].max(tiles.values[t][3]) * f;
    order.sort_unstable_by(|a, b| reach(b).total_cmp(&reach(a)));
    let (mut parent, mut own) = (0.0f32, 0.0f32);
    for (f, t) in order {
        let [_, _, d0, dc] = tiles.values[t];
        if d0 * hs * f <= parent && dc * hs * f <= own {
            continue;
        }
        let [x0, z0, x1, z1] = tiles.groups[t];
        for gz in z0..z1 {
            for gx in x0..x1 {
                let (d0, dc) = group_deviations(mm, b.lod, gx as usize, gz as usize);
                if d0 == 0.0 && dc == 0.0 {
                    continue;
                }
                let [lo, hi] = mm.get(b.lod + 1, gx as usize, gz as usize);
                let f = scale([gx, gz, gx + 1, gz + 1], lo, hi);
                parent = parent.max(d0 * hs * f);
                own = own.max(dc * hs * f);
            }
        }
    }
    (parent, own)
}

/// The factor that the selection's own (possibly stale-corrected) errors give: 0 when the
/// parent's error is delta (the moment it split), 1 when the block's own error is delta
/// (the moment it splits in turn), linear in between. The selection decides splits with
/// these errors, so the morph is continuous across them even with stale error data,
/// where the fresh bound alone would let a block about to split sit on its parent's
/// surface.
fn selection_factor([own, parent]: [f32; 2], delta: f32) -> f32 {
    if parent.is_finite() && parent > delta && parent > own {
        ((parent - delta) / (parent - own)).clamp(0.0, 1.0)
    } else {
        0.0
    }
}

/// Steps of the factor search (in units of `1 / MORPH_ONE`).
const STEP: u16 = MORPH_ONE / 64;

/// The least factor `>= current` (in steps of [`STEP`]) that meets `delta`, with each
/// edge factor given as a function of it, if any.
fn least_factor(c: &MorphCost, current: u16, edges: impl Fn(u16) -> [u16; 4], delta: f32) -> Option<u16> {
    let mut q = current;
    loop {
        let e = edges(q);
        // Everything at factor 1 is the selection's own surface, which it bounds.
        if c.bound(morph_value(q), e.map(morph_value)) <= delta || (q == MORPH_ONE && e == [MORPH_ONE; 4]) {
            return Some(q);
        }
        if q == MORPH_ONE {
            return None;
        }
        q = (q + STEP - q % STEP).min(MORPH_ONE);
    }
}

/// A block reaches its own surface at the latest when its parent's fresh error is this
/// many times delta (linearly from its split, where the parent's error is delta), or when
/// the selection's errors say so ([`selection_factor`]), or before, if the bound asks for
/// it. Without these a block would sit at exactly delta until it splits.
pub const MORPH_RANGE: f32 = 2.0;

/// Rounds of raising before giving up on morphing this frame (factor 1 everywhere).
const MAX_ROUNDS: usize = 200;

/// Per drawn block, the sides whose vertices never morph (bit `s` for side `s`): see
/// `EdgeVars`.
pub fn fixed_edges(layout: &BlockLayout, t: &Traversal) -> Vec<u8> {
    let root = layout.root_lod();
    let edges = EdgeVars::new(layout, t, |i| t.blocks[i].lod < root);
    (0..t.blocks.len()).map(|i| edges.fixed(i)).collect()
}

/// Sets every block's morph factors (the renderer's rule).
pub fn assign(
    hf: &Heightfield,
    mm: &MinMaxPyramid,
    caches: &BlockCaches,
    layout: &BlockLayout,
    cam: &Camera,
    delta: f32,
    t: &mut Traversal,
) {
    assign_with(hf, mm, caches, layout, cam, delta, t, MorphRule::Bounded);
}

/// Sets every block's morph factors by `rule`.
#[allow(clippy::too_many_arguments)]
pub fn assign_with(
    hf: &Heightfield,
    mm: &MinMaxPyramid,
    caches: &BlockCaches,
    layout: &BlockLayout,
    cam: &Camera,
    delta: f32,
    t: &mut Traversal,
    rule: MorphRule,
) {
    let root = layout.root_lod();
    let n = t.blocks.len();
    let edges = EdgeVars::new(layout, t, |i| t.blocks[i].lod < root);
    // The root has no parent to morph from.
    // Cheap edge terms first; the exact ones (cached per block, costly the first time a
    // block is seen) only for blocks that the cheap ones hold back. Each block's cost is
    // its own (the caches are shared behind a lock), so they are computed on every core
    // of the caller's pool: on a GPU the frame waits for this loop, not for the GPU.
    let mut costs: Vec<Option<MorphCost>> = map_in_pool(&t.blocks, |i, b| {
        (b.lod < root).then(|| cost(hf, mm, caches, layout, cam, delta, b, edges.fixed(i), EdgeTerms::Cheap))
    });
    let mut exact = vec![false; n];
    // Start from the ramp; the bound may ask for more.
    let mut q: Vec<u16> = costs
        .iter()
        .enumerate()
        .map(|(i, c)| match c {
            Some(_) if rule == MorphRule::ParentSurface => 0,
            Some(c) => {
                let ramp = ((c.parent / delta - 1.0) / (MORPH_RANGE - 1.0)).clamp(0.0, 1.0);
                (ramp.max(selection_factor(t.selection_errors.get(i).copied().unwrap_or_default(), delta))
                    * MORPH_ONE as f32)
                    .ceil() as u16
            }
            None => MORPH_ONE,
        })
        .collect();
    let mut e = edges.start(&q);
    // The exact terms of the blocks the cheap ones hold back from the start, on every
    // core. The rounds below take them where they would compute them, so the factors are
    // the same as computing each one there; a block held back only later computes its own.
    let mut exact_ahead: Vec<Option<MorphCost>> = vec![None; n];
    if rule == MorphRule::Bounded || rule == MorphRule::Underpaid {
        let fits_at_start = |i: usize, c: &MorphCost| {
            let now = edges.values(i, &e);
            c.bound(morph_value(q[i]), now.map(morph_value)) <= delta || (q[i] == MORPH_ONE && now == [MORPH_ONE; 4])
        };
        let held: Vec<usize> = (0..n).filter(|&i| costs[i].is_some_and(|c| !fits_at_start(i, &c))).collect();
        let ahead: Vec<MorphCost> = map_in_pool(&held, |_, &i| {
            cost(hf, mm, caches, layout, cam, delta, &t.blocks[i], edges.fixed(i), EdgeTerms::Exact)
        });
        assert_eq!(ahead.len(), held.len());
        for (i, c) in held.into_iter().zip(ahead) {
            exact_ahead[i] = Some(c);
        }
    }
    let mut settled = false;
    for _ in 0..MAX_ROUNDS {
        if rule == MorphRule::ParentSurface {
            settled = true;
            break;
        }
        let mut changed = false;
        for i in 0..n {
            let Some(cheap) = costs[i] else { continue };
            let now = edges.values(i, &e);
            // Everything at factor 1 is the selection's own surface, which it bounds.
            let fits = |c: &MorphCost| {
                c.bound(morph_value(q[i]), now.map(morph_value)) <= delta
                    || (q[i] == MORPH_ONE && now == [MORPH_ONE; 4])
            };
            if fits(&cheap) {
                continue;
            }
            if !exact[i] {
                exact[i] = true;
                let c = cheap.min(&exact_ahead[i].take().unwrap_or_else(|| {
                    cost(hf, mm, caches, layout, cam, delta, &t.blocks[i], edges.fixed(i), EdgeTerms::Exact)
                }));
                costs[i] = Some(c);
                if fits(&c) {
                    continue;
                }
            }
            let Some(c) = &costs[i] else { continue };
            changed = true;
            // Raise its factor and its edges together (a shared edge changes the block
            // across, checked in the next round). At factor 1 with every edge at 1 it
            // always fits.
            let with_edges = |f: u16| edges.raised(i, &e, f);
            let f = least_factor(c, q[i], with_edges, delta).unwrap_or(MORPH_ONE);
            q[i] = f;
            edges.raise(i, &mut e, f);
        }
        if !changed {
            settled = true;
            break;
        }
    }
    let mut block_edges: Vec<[u16; 4]> = (0..n).map(|i| edges.values(i, &e)).collect();
    if !settled {
        q.fill(MORPH_ONE);
        block_edges.fill([MORPH_ONE; 4]);
    }
    if rule == MorphRule::Underpaid {
        for (i, (f, be)) in q.iter_mut().zip(block_edges.iter_mut()).enumerate() {
            *f /= 2;
            for (s, e) in be.iter_mut().enumerate() {
                if edges.fixed(i) & (1 << s) == 0 {
                    *e /= 2;
                }
            }
        }
    }
    t.morphing = 0;
    for (i, b) in t.blocks.iter_mut().enumerate() {
        b.morph = q[i];
        b.edge_morph = block_edges[i];
        if q[i] < MORPH_ONE || block_edges[i].iter().any(|&e| e < MORPH_ONE) {
            t.morphing += 1;
            if let Some(c) = &costs[i] {
                t.max_block_error = t.max_block_error.max(c.bound(morph_value(q[i]), block_edges[i].map(morph_value)));
            }
        }
    }
}

/// The edges' morph factors: one variable per edge between blocks, shared by the blocks
/// on both sides, so that they draw the same vertices:
/// - an edge between two blocks of the same LOD: its odd vertices, from the parent
///   surface to their own samples; it starts at the larger of the two blocks' factors
///   (measured on the CPU displacement test: starting at the smaller one, the coarser
///   edge while either block has just split, moved the low flight's surface 0.24 of
///   the unmorphed displacement against 0.20);
/// - a block's edge next to finer blocks: the coarse block's odd edge vertices, which the
///   finer blocks' collapsed vertices follow ([`crate::lod::block::block_vertex`]); it starts
///   at the coarse block's factor, which is what the edge becomes when the finer blocks
///   merge into one of its LOD;
/// - an edge with no drawn block across: the block's own, starting at its factor.
///
/// An edge is fixed (not morphing, factor 1) when it belongs to a block that does not
/// morph (the root), or lies between blocks whose LODs differ by `m` or more (`k = 2^m +
/// 1`): then a finer block's corner may sit on an odd vertex of the coarser edge, and
/// corners never morph ([`crate::lod::traversal::resolve_corners`]). With a smaller difference
/// every finer corner falls on an even vertex of the coarser edge.
struct EdgeVars {
    /// Per block and side: the variable, or `None` when fixed.
    var: Vec<[Option<usize>; 4]>,
    /// What each variable starts from: the factors of the blocks whose maximum it takes.
    start: Vec<Vec<usize>>,
}

impl EdgeVars {
    fn new(layout: &BlockLayout, t: &Traversal, morphs: impl Fn(usize) -> bool) -> Self {
        let n = t.blocks.len();
        let index: HashMap<(u32, u32, u32), usize> =
            t.blocks.iter().enumerate().map(|(i, b)| ((b.lod, b.bx, b.bz), i)).collect();
        let [cells, rows] = layout.cells().map(|c| c as i64);
        let mut var = vec![[None; 4]; n];
        let mut start: Vec<Vec<usize>> = Vec::new();
        let mut new_var = |from: Vec<usize>| {
            start.push(from);
            Some(start.len() - 1)
        };
        // Edges whose variable the block across creates, linked once every block's own
        // variables exist: (block, side, block across).
        let (mut coarser, mut same) = (Vec::new(), Vec::new());
        for (i, b) in t.blocks.iter().enumerate() {
            if !morphs(i) {
                continue;
            }
            let span = 1i64 << b.lod;
            for (s, (nx, nz)) in b.cells_across().into_iter().enumerate() {
                if nx < 0 || nz < 0 || nx >= cells || nz >= rows {
                    var[i][s] = new_var(vec![i]);
                    continue;
                }
                let l = t.lod_map[(nz * cells + nx) as usize];
                if l == b.lod as i8 {
                    let l = l as u32;
                    match index.get(&(l, (nx >> l) as u32, (nz >> l) as u32)) {
                        // Created by the block across, which comes first.
                        Some(&j) if j < i => same.push((i, s, j)),
                        Some(&j) if morphs(j) => var[i][s] = new_var(vec![i, j]),
                        Some(_) => {}
                        None => var[i][s] = new_var(vec![i]),
                    }
                } else if l > b.lod as i8 {
                    let l = l as u32;
                    if l - b.lod < layout.m {
                        if let Some(&c) = index.get(&(l, (nx >> l) as u32, (nz >> l) as u32)) {
                            coarser.push((i, s, c));
                        }
                    }
                } else {
                    // Finer blocks (some perhaps culled) line the edge.
                    let (dx, dz) = if s % 2 == 0 { (1, 0) } else { (0, 1) };
                    let finest = (0..span)
                        .map(|d| t.lod_map[((nz + d * dz) * cells + nx + d * dx) as usize])
                        .filter(|&l| l >= 0)
                        .min();
                    match finest {
                        Some(f) if b.lod - f as u32 >= layout.m => {}
                        _ => var[i][s] = new_var(vec![i]),
                    }
                }
            }
        }
        for (i, s, j) in same.into_iter().chain(coarser) {
            var[i][s] = if morphs(j) { var[j][(s + 2) % 4] } else { None };
        }
        EdgeVars { var, start }
    }

    /// Sides of block `i` that do not morph.
    fn fixed(&self, i: usize) -> u8 {
        (0..4).filter(|&s| self.var[i][s].is_none()).fold(0, |m, s| m | 1 << s)
    }

    /// Every variable at its start, given the blocks' factors.
    fn start(&self, q: &[u16]) -> Vec<u16> {
        self.start.iter().map(|from| from.iter().map(|&i| q[i]).max().unwrap_or(MORPH_ONE)).collect()
    }

    /// Block `i`'s edge factors (1 on fixed sides).
    fn values(&self, i: usize, e: &[u16]) -> [u16; 4] {
        self.var[i].map(|v| v.map_or(MORPH_ONE, |v| e[v]))
    }

    /// Block `i`'s edge factors with each of its variables raised to at least `f`.
    fn raised(&self, i: usize, e: &[u16], f: u16) -> [u16; 4] {
        self.var[i].map(|v| v.map_or(MORPH_ONE, |v| e[v].max(f)))
    }

    fn raise(&self, i: usize, e: &mut [u16], f: u16) {
        for v in self.var[i].iter().flatten() {
            e[*v] = e[*v].max(f);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::lod::heightfield::HeightFormat;
    use glam::Vec3;

    /// Every parent group's term, no tiles: the maximum the pruned search must find.
    fn interior_all_groups(
        hf: &Heightfield,
        mm: &MinMaxPyramid,
        layout: &BlockLayout,
        cam: &Camera,
        b: &DrawBlock,
        per_group: f32,
    ) -> (f32, f32) {
        let [ga, gb, ge, gf] = interior_groups(mm, layout, b);
        let (hs, group) = (hf.height_scale, 1i64 << (b.lod + 1));
        let (mut parent, mut own) = (0.0f32, 0.0f32);
        for gz in gb..gf {
            for gx in ga..ge {
                let (d0, dc) = group_deviations(mm, b.lod, gx, gz);
                let [lo, hi] = mm.get(b.lod + 1, gx, gz);
                let (x0, z0) = (gx as i64 * group, gz as i64 * group);
                let (gmin, gmax) = hf.world_box(x0, z0, x0 + group, z0 + group, [lo * hs, hi * hs]);
                let f = per_group / distance_to_aabb(cam.position, gmin, gmax).max(cam.near);
                parent = parent.max(d0 * hs * f);
                own = own.max(dc * hs * f);
            }
        }
        (parent, own)
    }

    /// Rough terrain with one spike (the group most likely to be skipped wrongly when its
    /// tile is far), cameras inside, above and beside the blocks, every block of three
    /// LODs and two block sizes: the pruned maximum is the maximum over all groups, bit
    /// for bit.
    #[test]
    fn tiles_find_the_maximum_over_all_groups() {
        let side = 257;
        let s: Vec<f32> = (0..side * side)
            .map(|i| {
                let (x, z) = (i % side, i / side);
                let spike = if (x, z) == (200, 37) { 900.0 } else { 0.0 };
                ((x * 7919 + z * 104_729) % 97) as f32 + (x as f32 * 0.05).sin() * 60.0 + spike
            })
            .collect();
        let hf = Heightfield::embed("t", side, side, &s, HeightFormat::Float32, 1.0, 2.0).unwrap();
        let mm = MinMaxPyramid::build(&hf);
        let mut compared = 0;
        let mut differ_from_block_box = 0;
        for k in [17, 33] {
            let layout = BlockLayout::of(&hf, k).unwrap();
            let cams = [
                Vec3::new(201.0, 40.0, 38.0),
                Vec3::new(10.0, 600.0, 250.0),
                Vec3::new(-300.0, 5.0, 128.0),
                Vec3::new(128.0, 2000.0, 128.0),
            ];
            for p in cams {
                let cam = Camera::look_at(p, Vec3::new(128.0, 0.0, 128.0), 60.0, 640, 480, 0.05);
                for lod in 0..3.min(layout.root_lod()) {
                    let [nx, nz] = layout.blocks(lod);
                    for bz in 0..nz as u32 {
                        for bx in 0..nx as u32 {
                            let b = DrawBlock::new(lod, bx, bz);
                            let want = interior_all_groups(&hf, &mm, &layout, &cam, &b, 1.5);
                            assert_eq!(
                                interior(&hf, &mm, &BlockCaches::default(), &layout, &cam, &b, 1.5),
                                want,
                                "k {k}, {b:?}, camera {p}"
                            );
                            let (min, max) = block_aabb(&hf, &mm, &layout, lod, bx, bz);
                            let coarse = 1.5 / distance_to_aabb(cam.position, min, max).max(cam.near);
                            if want.0 > 0.0 && want.0 < 0.99 * coarse * hf.height_scale * mm_max_d0(&mm, &layout, &b) {
                                differ_from_block_box += 1;
                            }
                            compared += 1;
                        }
                    }
                }
            }
        }
        assert!(compared > 500, "{compared}");
        // The per-group distances matter (a whole-block bound would be looser): the case
        // the pruning must get right.
        assert!(differ_from_block_box > 50, "{differ_from_block_box} of {compared}");
    }

    fn mm_max_d0(mm: &MinMaxPyramid, layout: &BlockLayout, b: &DrawBlock) -> f32 {
        let [ga, gb, ge, gf] = interior_groups(mm, layout, b);
        (gb..gf)
            .flat_map(|gz| (ga..ge).map(move |gx| (gx, gz)))
            .map(|(gx, gz)| mm.deviation(b.lod + 1, gx, gz))
            .fold(0.0, f32::max)
    }
}
