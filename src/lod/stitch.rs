//! What stitching costs in the bound (SPEC section 5, cracks). An edge next to a coarser
//! block collapses its in-between vertices onto the coarser block's vertices (or, when the
//! whole edge lies inside one coarse segment, moves them onto it): watertight with no
//! T-junction, but the first strip of quads along that edge is re-triangulated with fan
//! triangles whose surface neither block's error covers. This module measures that strip
//! exactly: `max |H - S|` over the samples under the stitched strip `S`, which depends on
//! the block and its neighbours' LODs but not on the camera, so it is computed once per
//! configuration and cached, for both ends of the morph (see `morph.rs`). The traversal
//! projects it like any world-space deviation.

use crate::lod::block::{block_vertex, BlockLayout, DrawBlock, EDGE_CORNERS};
use crate::lod::block_cache::BoundedCache;
use crate::lod::heightfield::{Heightfield, RawSamples};
use crate::lod::pyramid::MinMaxPyramid;
use std::ops::RangeInclusive;

/// Deviation of the stitched strips of one block, in raw height units.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct StripDeviation {
    /// `max |H - S|` over the strip along each edge (north, east, south, west); 0 for
    /// edges without a coarser neighbour.
    pub edge: [f32; 4],
    /// Raw height range of the stitched strips' surface: vertices moved onto a coarse
    /// segment may leave the block's own min/max (the AABB the bound projects with).
    pub lo: f32,
    pub hi: f32,
}

impl StripDeviation {
    pub fn max(&self) -> f32 {
        self.edge.iter().cloned().fold(0.0, f32::max)
    }
}

/// The block size (`m`), the block (LOD, position, neighbours, corners; unmorphed) and
/// the edges measured.
type Key = (u32, DrawBlock, u8);

/// Strip deviations and edge regions already computed, by block and neighbour strides.
/// None depends on the camera, so a block keeps its entries while it stays drawn.
#[derive(Clone, Debug, Default)]
pub struct StitchCache {
    strips: BoundedCache<Key, StripDeviation>,
    regions: BoundedCache<Key, EdgeRegions>,
    bounds: BoundedCache<Key, EdgeRegions>,
}

/// Exact deviation (raw units) of a block's edge regions in every combination of the
/// morph states of the vertex groups they touch (`morph.rs`): the strip along each edge
/// without its corner quads touches the interior vertices (factor `f`) and that edge's
/// (`e`); a corner quad touches the interior and both edges meeting there. Vertices on
/// the edges in `fixed` never morph.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct EdgeRegions {
    /// Per edge and segment of its strip ([`strip_segment`]), state `2 f + e` (0:
    /// parent, 1: own): each segment is projected from its own box.
    pub side: [[[f32; 4]; STRIP_SEGMENTS]; 4],
    /// Per corner (NW, NE, SE, SW, between the edges in [`CORNER_EDGES`]), state
    /// `4 f + 2 e_a + e_b`.
    pub corner: [[f32; 8]; 4],
    /// Raw height range of the vertices in every state.
    pub lo: f32,
    pub hi: f32,
}

/// Segments a strip is measured in, so that each is projected from its own distance.
pub const STRIP_SEGMENTS: usize = 8;

/// The segment of quad `t` (0..=`last`, along the edge) of a strip.
pub fn strip_segment(t: u32, last: u32) -> usize {
    (t as usize * STRIP_SEGMENTS) / (last as usize + 1)
}

/// Quad `t` (0..=`last`) of the first row along edge `e`.
fn strip_quad(e: usize, t: u32, last: u32) -> (u32, u32) {
    match e {
        0 => (t, 0),
        1 => (last, t),
        2 => (t, last),
        _ => (0, t),
    }
}

/// The two edges meeting at each corner (NW, NE, SE, SW).
pub const CORNER_EDGES: [[usize; 2]; 4] = [[0, 3], [0, 1], [2, 1], [2, 3]];

impl StitchCache {
    /// The edge regions of `b` (its morph factors ignored) whose edges in `fixed` do not
    /// morph.
    pub fn regions(
        &self,
        hf: &Heightfield,
        mm: &MinMaxPyramid,
        layout: &BlockLayout,
        b: &DrawBlock,
        fixed: u8,
    ) -> EdgeRegions {
        self.regions.get_or_compute((layout.m, b.unmorphed(), fixed), || edge_regions(hf, mm, layout, b, fixed))
    }

    /// [`edge_regions_bound`] of `b` (its morph factors ignored), cached: it is asked for
    /// every drawn block every frame.
    pub fn regions_bound(
        &self,
        hf: &Heightfield,
        mm: &MinMaxPyramid,
        layout: &BlockLayout,
        b: &DrawBlock,
        fixed: u8,
    ) -> EdgeRegions {
        self.bounds
            .get_or_compute((layout.m, b.unmorphed(), fixed), || edge_regions_bound(hf, mm, self, layout, b, fixed))
    }

    /// The stitched strips of `b` (the edges next to a coarser block), unmorphed.
    pub fn get(&self, hf: &Heightfield, layout: &BlockLayout, b: &DrawBlock) -> StripDeviation {
        let sides = coarser_sides(b);
        self.strips
            .get_or_compute((layout.m, b.unmorphed(), sides), || strip_deviation(hf, layout, &b.unmorphed(), sides))
    }
}

/// Bit `e` set for each edge `e` next to a coarser block.
pub fn coarser_sides(b: &DrawBlock) -> u8 {
    (0..4).filter(|&e| b.coarser[e] > 0).fold(0, |m, e| m | 1 << e)
}

/// Exact deviation of the strips of `b` along the edges in `sides`: the first row of
/// quads along an edge, where collapsed (stitched) vertices and edge vertices with their
/// own morph factor sit.
pub fn strip_deviation(hf: &Heightfield, layout: &BlockLayout, b: &DrawBlock, sides: u8) -> StripDeviation {
    let mut out = StripDeviation { edge: [0.0; 4], lo: f32::INFINITY, hi: f32::NEG_INFINITY };
    let last = layout.k() - 2; // last quad index
    for e in 0..4 {
        if sides & (1 << e) == 0 {
            continue;
        }
        let mut m = 0.0f32;
        for t in 0..=last {
            let (u, v) = strip_quad(e, t, last);
            let vert = |uu: u32, vv: u32| block_vertex(hf, layout, b, uu, vv);
            let (a, c, i, g) = (vert(u, v), vert(u + 1, v), vert(u + 1, v + 1), vert(u, v + 1));
            for tri in [[a, c, i], [a, i, g]] {
                for p in &tri {
                    out.lo = out.lo.min(p.2);
                    out.hi = out.hi.max(p.2);
                }
                m = m.max(triangle_deviation(hf, &tri));
            }
        }
        out.edge[e] = m;
    }
    if out.lo > out.hi {
        out.lo = 0.0;
        out.hi = 0.0;
    }
    out
}

/// See [`EdgeRegions`]. The triangulation is the same in every state (only heights
/// move), so each sample's barycentric weights are found once for all states. Strip
/// quads that [`edge_regions_bound`]'s per-quad terms show cannot matter are skipped; the
/// result is the same.
pub fn edge_regions(
    hf: &Heightfield,
    mm: &MinMaxPyramid,
    layout: &BlockLayout,
    b: &DrawBlock,
    fixed: u8,
) -> EdgeRegions {
    edge_regions_pruned(hf, mm, layout, b, fixed).0
}

/// [`edge_regions`] and the number of strip quads it skipped.
fn edge_regions_pruned(
    hf: &Heightfield,
    mm: &MinMaxPyramid,
    layout: &BlockLayout,
    b: &DrawBlock,
    fixed: u8,
) -> (EdgeRegions, usize) {
    use crate::lod::block::MORPH_ONE;
    let last = layout.k() - 2; // last quad index
    let mut out = EdgeRegions { lo: f32::INFINITY, hi: f32::NEG_INFINITY, ..Default::default() };
    let state = |f: bool, edges: &[(usize, bool)]| {
        let q = |on: bool| if on { MORPH_ONE } else { 0 };
        let mut s = DrawBlock { morph: q(f), edge_morph: [MORPH_ONE; 4], ..*b };
        for &(e, on) in edges {
            if fixed & (1 << e) == 0 {
                s.edge_morph[e] = q(on);
            }
        }
        s
    };
    // Quad (u, v)'s deviation in each of the states `s`.
    let mut quad_dev = |s: &[DrawBlock], u: u32, v: u32, dev: &mut [f32]| {
        let corners = [(u, v), (u + 1, v), (u + 1, v + 1), (u, v + 1)];
        let mut pos = [(0i64, 0i64); 4];
        let mut heights = [[0.0f32; 4]; 8];
        for (st, block) in s.iter().enumerate() {
            for (c, &(uu, vv)) in corners.iter().enumerate() {
                let (x, z, h) = block_vertex(hf, layout, block, uu, vv);
                debug_assert!(st == 0 || pos[c] == (x, z), "a morph state moved a vertex in x or z");
                pos[c] = (x, z);
                heights[st][c] = h;
                out.lo = out.lo.min(h);
                out.hi = out.hi.max(h);
            }
        }
        for tri in [[0, 1, 2], [0, 2, 3]] {
            let p = tri.map(|c| pos[c]);
            let h: [[f32; 3]; 8] = std::array::from_fn(|st| tri.map(|c| heights[st][c]));
            triangle_deviation_states(hf, p, &h[..s.len()], dev);
        }
    };
    let mut dev = [0.0f32; 8];
    // A strip quad whose cheap bound cannot raise its segment's maximum in any state
    // leaves the regions as they are: skipped, the highest bounds first. Worth it from
    // LOD 2 (16 samples a quad and state against 4 vertices), and only along free edges
    // (a stitched strip's bound is the whole strip's deviation, rarely below).
    let mut bounds = QuadBounds::new(hf, mm, layout, b, fixed);
    let mut order: Vec<(usize, [f32; 4], u32)> = Vec::with_capacity(last as usize);
    let mut skipped = 0;
    for e in 0..4 {
        let states: [DrawBlock; 4] = std::array::from_fn(|st| state(st & 2 != 0, &[(e, st & 1 != 0)]));
        let prune = b.lod >= 2 && b.coarser[e] == 0;
        order.clear();
        for t in 1..last {
            let (u, v) = strip_quad(e, t, last);
            let bound = if prune { bounds.strip(e, u, v, 0.0) } else { [f32::INFINITY; 4] };
            order.push((strip_segment(t, last), bound, t));
        }
        if prune {
            order.sort_by(|a, b| a.0.cmp(&b.0).then(b.1[0].max(b.1[1]).total_cmp(&a.1[0].max(a.1[1]))));
        }
        for &(g, bound, t) in &order {
            if bound.iter().zip(&out.side[e][g]).all(|(b, m)| b + bound_slack(*b) <= *m) {
                skipped += 1;
                continue;
            }
            let (u, v) = strip_quad(e, t, last);
            dev[..4].fill(0.0);
            quad_dev(&states, u, v, &mut dev[..4]);
            let m = &mut out.side[e][g];
            for (m, d) in m.iter_mut().zip(&dev) {
                *m = m.max(*d);
            }
        }
    }
    for (c, [ea, eb]) in CORNER_EDGES.iter().copied().enumerate() {
        let (u, v) = [(0, 0), (last, 0), (last, last), (0, last)][c];
        let states: [DrawBlock; 8] =
            std::array::from_fn(|st| state(st & 4 != 0, &[(ea, st & 2 != 0), (eb, st & 1 != 0)]));
        dev.fill(0.0);
        quad_dev(&states, u, v, &mut dev);
        out.corner[c] = dev;
    }
    // The skipped quads' vertices count in the range: the bound measured them.
    if bounds.lo <= bounds.hi {
        (out.lo, out.hi) = (out.lo.min(bounds.lo), out.hi.max(bounds.hi));
    }
    if out.lo > out.hi {
        out.lo = 0.0;
        out.hi = 0.0;
    }
    (out, skipped)
}

/// How far a cheap bound may fall under the exact value by rounding alone (the two sum
/// and interpolate in different orders): far above f32's, far below a pixel's worth.
fn bound_slack(x: f32) -> f32 {
    1e-4 * x.abs().max(1.0)
}

/// A cheap upper bound on [`edge_regions`], for blocks seen for the first time (the exact
/// regions cost `O(k * stride^2)` samples per state; this costs `O(k)` vertices), quad
/// by quad. In any state the drawn surface is the unmorphed one with each vertex moved
/// by its own group's displacement times `1 - factor`, and a point of a triangle moves by
/// at most its vertices' largest move, so a quad's deviation is at most the unmorphed
/// surface's there (the quad's `D_j`, or the stitched strip's exact deviation along an
/// edge next to a coarser block, which the selection has measured) plus the largest move
/// of a vertex group it touches, scaled by that group's `1 - factor`.
///
/// Read from the other end, with every group at factor 0 a quad whose vertices are all
/// the block's own (no coarser block across, no fixed edge, no resolved corner) lies on
/// its parent's surface, its parent cell's two triangles: there the deviation is at most
/// that cell's `D_{j+1}` plus the largest move of a group at factor 1. Each state takes
/// the smaller of the two; a block that has just split is near factor 0, where the first
/// bound is loosest and the second tightest.
pub fn edge_regions_bound(
    hf: &Heightfield,
    mm: &MinMaxPyramid,
    strips: &StitchCache,
    layout: &BlockLayout,
    b: &DrawBlock,
    fixed: u8,
) -> EdgeRegions {
    let last = layout.k() - 2; // last quad index
    let stitched = if coarser_sides(b) != 0 { strips.get(hf, layout, b).edge } else { [0.0; 4] };
    let mut q = QuadBounds::new(hf, mm, layout, b, fixed);
    let mut out = EdgeRegions::default();
    for (e, &stitched) in stitched.iter().enumerate() {
        for t in 1..last {
            let (u, v) = strip_quad(e, t, last);
            let quad = q.strip(e, u, v, stitched);
            for (m, q) in out.side[e][strip_segment(t, last)].iter_mut().zip(quad) {
                *m = m.max(q);
            }
        }
    }
    for (c, [ea, eb]) in CORNER_EDGES.iter().copied().enumerate() {
        let (u, v) = [(0, 0), (last, 0), (last, last), (0, last)][c];
        let d = q.own_dev(u, v).max(stitched[ea]).max(stitched[eb]);
        // A corner leaves its sample only inside a coarser block's edge
        // (`traversal::resolve_corners`), which rules the parent's surface out already.
        let p = q.parent_dev(u, v, &[ea, eb]);
        let (mut int, mut a, mut bm) = (0.0f32, 0.0f32, 0.0f32);
        for (vu, vv) in [(u, v), (u + 1, v), (u + 1, v + 1), (u, v + 1)] {
            match q.moves(vu, vv) {
                (m, Some(g)) if g == ea => a = a.max(m),
                (m, Some(g)) if g == eb => bm = bm.max(m),
                (m, _) => int = int.max(m),
            }
        }
        for st in 0..8 {
            // The moves of the groups at 0 (from the own surface) and at 1 (from the
            // parent's).
            let at = |on: bool, m: f32| if on { (0.0, m) } else { (m, 0.0) };
            let (i, ai, bi) = (at(st & 4 != 0, int), at(st & 2 != 0, a), at(st & 1 != 0, bm));
            out.corner[c][st] = (d + i.0.max(ai.0).max(bi.0)).min(p + i.1.max(ai.1).max(bi.1));
        }
    }
    (out.lo, out.hi) = q.range();
    out
}

/// The terms of [`edge_regions_bound`], quad by quad: each quad's own and parent
/// deviations from the pyramid, and its vertices' moves between factors 0 and 1 (with
/// the heights they take, the vertices' range in every state).
struct QuadBounds<'a> {
    hf: &'a Heightfield,
    mm: &'a MinMaxPyramid,
    layout: &'a BlockLayout,
    b: &'a DrawBlock,
    fixed: u8,
    one: DrawBlock,
    zero: DrawBlock,
    /// Each vertex is shared by up to four quads of the strips: measured once.
    measured: Vec<Option<f32>>,
    lo: f32,
    hi: f32,
}

impl<'a> QuadBounds<'a> {
    fn new(hf: &'a Heightfield, mm: &'a MinMaxPyramid, layout: &'a BlockLayout, b: &'a DrawBlock, fixed: u8) -> Self {
        use crate::lod::block::MORPH_ONE;
        let zero = DrawBlock {
            morph: 0,
            edge_morph: std::array::from_fn(|s| if fixed & (1 << s) != 0 { MORPH_ONE } else { 0 }),
            ..*b
        };
        let k = layout.k() as usize;
        let measured = vec![None; k * k];
        QuadBounds {
            hf,
            mm,
            layout,
            b,
            fixed,
            one: b.unmorphed(),
            zero,
            measured,
            lo: f32::INFINITY,
            hi: f32::NEG_INFINITY,
        }
    }

    /// `D_j` of quad (u, v): the unmorphed surface's deviation where no coarser block
    /// is stitched to it.
    fn own_dev(&self, u: u32, v: u32) -> f32 {
        let (ox, oz) = self.b.origin(self.layout);
        let st = self.b.stride();
        if self.b.lod == 0 {
            0.0
        } else {
            self.mm.deviation(self.b.lod, (ox / st + u) as usize, (oz / st + v) as usize)
        }
    }

    /// The parent cell's `D_{j+1}` under quad (u, v), where every state-0 vertex of the
    /// quad is on the parent's surface (the edges in `own` free to morph, from the block's
    /// own vertices); infinite where not, so that only the own surface's bound counts.
    fn parent_dev(&self, u: u32, v: u32, own: &[usize]) -> f32 {
        let (b, mm) = (self.b, self.mm);
        let free = own.iter().all(|&e| self.fixed & (1 << e) == 0 && b.coarser[e] == 0);
        let (ox, oz) = b.origin(self.layout);
        let st = b.stride();
        let (px, pz) = (((ox / st + u) / 2) as usize, ((oz / st + v) / 2) as usize);
        if !free || b.lod >= mm.n {
            return f32::INFINITY;
        }
        let [cells, rows] = mm.cells(b.lod + 1);
        if px < cells && pz < rows {
            mm.deviation(b.lod + 1, px, pz)
        } else {
            f32::INFINITY
        }
    }

    /// How far vertex (u, v) moves between factor 0 and 1 of its group, and the group:
    /// Some(edge) or None for the interior (the corners never move).
    fn moves(&mut self, u: u32, v: u32) -> (f32, Option<usize>) {
        let kk = self.layout.k() - 1; // last vertex index
        let slot = &mut self.measured[(v * (kk + 1) + u) as usize];
        let m = match *slot {
            Some(m) => m,
            None => {
                let a = block_vertex(self.hf, self.layout, &self.one, u, v).2;
                let z = block_vertex(self.hf, self.layout, &self.zero, u, v).2;
                (self.lo, self.hi) = (self.lo.min(a.min(z)), self.hi.max(a.max(z)));
                *slot.insert((a - z).abs())
            }
        };
        let group = [(0, v == 0), (2, v == kk), (1, u == kk), (3, u == 0)].into_iter().find(|g| g.1).map(|g| g.0);
        (m, group)
    }

    /// The bound on strip quad (u, v) along edge `e` in each state `2 f + e`; `stitched`
    /// is the edge's exact stitched deviation, used where a coarser block is across.
    fn strip(&mut self, e: usize, u: u32, v: u32, stitched: f32) -> [f32; 4] {
        let d = if self.b.coarser[e] > 0 { stitched } else { self.own_dev(u, v) };
        let p = self.parent_dev(u, v, &[e]);
        let (mut int, mut edge) = (0.0f32, 0.0f32);
        for (vu, vv) in [(u, v), (u + 1, v), (u + 1, v + 1), (u, v + 1)] {
            let (m, group) = self.moves(vu, vv);
            if group == Some(e) {
                edge = edge.max(m);
            } else {
                int = int.max(m);
            }
        }
        [(d + int.max(edge)).min(p), (d + int).min(p + edge), (d + edge).min(p + int), d]
    }

    /// The raw height range of the vertices measured, in every state (0 and 0 for none).
    fn range(&self) -> (f32, f32) {
        if self.lo > self.hi {
            (0.0, 0.0)
        } else {
            (self.lo, self.hi)
        }
    }
}

/// `max |H - T|` over the integer samples inside triangle `t` (edges included); 0 for a
/// degenerate (collapsed) triangle, which covers nothing.
fn triangle_deviation(hf: &Heightfield, t: &[(i64, i64, f32); 3]) -> f32 {
    let mut m = [0.0f32];
    triangle_deviation_states(hf, t.map(|p| (p.0, p.1)), &[t.map(|p| p.2)], &mut m);
    m[0]
}

/// [`triangle_deviation`] of the triangle with corners `pos` and, in each state `s`, corner
/// heights `heights[s]`, raised into `dev[s]`.
fn triangle_deviation_states(hf: &Heightfield, pos: [(i64, i64); 3], heights: &[[f32; 3]], dev: &mut [f32]) {
    let z0 = pos.iter().map(|p| p.1).min().unwrap_or(0);
    let z1 = pos.iter().map(|p| p.1).max().unwrap_or(0);
    for z in z0..=z1 {
        // Only the row's samples inside the triangle (half of its box, for the
        // right-angled triangles of a quad) get weights.
        for x in inside_row(pos, z) {
            let w = crate::lod::geometry::barycentric(&pos, x, z);
            debug_assert!(w.is_some(), "({x}, {z}) is outside {pos:?}");
            let Some(w) = w else { continue };
            let raw = hf.raw_at(x, z);
            for (d, h) in dev.iter_mut().zip(heights) {
                *d = d.max((raw - crate::lod::geometry::weighted(w, *h)).abs());
            }
        }
    }
}

/// The samples of row `z` inside the triangle `pos` (edges included; none for a
/// degenerate one): exactly those for which [`crate::lod::geometry::barycentric`] finds weights.
/// Each of its three edge tests is linear in `x` along the row, `a x + b >= 0`, which
/// bounds `x` from one side (or, with `a = 0`, keeps or empties the row), in integers.
fn inside_row(pos: [(i64, i64); 3], z: i64) -> RangeInclusive<i64> {
    let [(x0, z0), (x1, z1), (x2, z2)] = pos;
    let det = (x1 - x0) * (z2 - z0) - (x2 - x0) * (z1 - z0);
    // An empty range.
    let empty = || RangeInclusive::new(1, 0);
    if det == 0 {
        return empty();
    }
    let s = det.signum();
    // barycentric's n1, n2 and n0 = det - n1 - n2 as a x + b, times the sign of det.
    let (a1, b1) = (z2 - z0, -x0 * (z2 - z0) - (x2 - x0) * (z - z0));
    let (a2, b2) = (-(z1 - z0), (x1 - x0) * (z - z0) + x0 * (z1 - z0));
    let (a0, b0) = (-a1 - a2, det - b1 - b2);
    let (mut lo, mut hi) = (pos.iter().map(|p| p.0).min().unwrap_or(0), pos.iter().map(|p| p.0).max().unwrap_or(0));
    for (a, b) in [(a1 * s, b1 * s), (a2 * s, b2 * s), (a0 * s, b0 * s)] {
        match a.signum() {
            // x >= ceil(-b / a)
            1 => lo = lo.max(-(b.div_euclid(a))),
            // x <= floor(b / -a)
            -1 => hi = hi.min(b.div_euclid(-a)),
            _ if b < 0 => return empty(),
            _ => {}
        }
    }
    lo..=hi
}

/// How far the drawn (stitched) surface of `b` departs from the block's own LOD-`j`
/// surface `L_j` (every vertex its own sample, split along the a-i diagonal) over each
/// edge's first row of quads, in raw units, and the raw height range of that row's drawn
/// vertices. For the streamed traversal, which holds no full-resolution samples: with
/// `D_j` the block's deviation, `|H - S| <= |H - L_j| + |L_j - S| <= D_j + edge[e]`.
///
/// Exact over the whole row, not only at samples: both surfaces are linear on each piece
/// of the overlay of their two triangulations, so the largest difference is at a vertex of
/// the intersection of a drawn triangle with a triangle of `L_j`.
pub fn strip_departure<S: RawSamples + ?Sized>(hf: &S, layout: &BlockLayout, b: &DrawBlock) -> StripDeviation {
    let last = layout.k() - 2;
    let own = DrawBlock::new(b.lod, b.bx, b.bz);
    let mut out = StripDeviation { lo: f32::INFINITY, hi: f32::NEG_INFINITY, ..Default::default() };
    let moved = corners_moved(hf, layout, b);
    for (e, edge) in out.edge.iter_mut().enumerate() {
        // A row differs from the block's own only along a coarser neighbour or where one
        // of its corners was moved onto a coarser edge.
        if b.coarser[e] == 0 && !EDGE_CORNERS[e].iter().any(|&c| moved[c]) {
            continue;
        }
        let mut drawn = Vec::with_capacity(2 * last as usize + 2);
        let mut flat = Vec::with_capacity(2 * last as usize + 2);
        let mut changed = false;
        for t in 0..=last {
            let (u, v) = strip_quad(e, t, last);
            let quad = |blk: &DrawBlock| {
                let p = |du: u32, dv: u32| block_vertex(hf, layout, blk, u + du, v + dv);
                let (a, c, i, g) = (p(0, 0), p(1, 0), p(1, 1), p(0, 1));
                [[a, c, i], [a, i, g]]
            };
            let (d, f) = (quad(b), quad(&own));
            changed |= d != f;
            for tri in &d {
                for p in tri {
                    out.lo = out.lo.min(p.2);
                    out.hi = out.hi.max(p.2);
                }
            }
            drawn.extend(d);
            flat.extend(f);
        }
        if changed {
            *edge = overlay_max_difference(&drawn, &flat);
        }
    }
    if out.lo > out.hi {
        (out.lo, out.hi) = (0.0, 0.0);
    }
    out
}

/// Which corners of `b` are drawn at another height than their own sample (resolved onto
/// a coarser neighbour's edge).
fn corners_moved<S: RawSamples + ?Sized>(hf: &S, layout: &BlockLayout, b: &DrawBlock) -> [bool; 4] {
    let last = layout.k() - 1;
    let (ox, oz) = b.origin(layout);
    let s = b.stride() as i64;
    let corners = [(0, 0), (last, 0), (last, last), (0, last)];
    std::array::from_fn(|c| {
        let (u, v) = corners[c];
        let (x, z) = (ox as i64 + u as i64 * s, oz as i64 + v as i64 * s);
        b.corner(c, hf, x, z).to_bits() != hf.raw_at(x, z).to_bits()
    })
}

/// `max |S(p) - T(p)|` over the region both triangle sets cover, `S` and `T` piecewise
/// linear over their triangles (degenerate ones cover nothing).
fn overlay_max_difference(s: &[[(i64, i64, f32); 3]], t: &[[(i64, i64, f32); 3]]) -> f32 {
    let bounds = |tri: &[(i64, i64, f32); 3]| {
        let xs = tri.map(|p| p.0);
        let zs = tri.map(|p| p.1);
        (*xs.iter().min().unwrap(), *xs.iter().max().unwrap(), *zs.iter().min().unwrap(), *zs.iter().max().unwrap())
    };
    let mut worst = 0.0f64;
    for a in s {
        let (ax0, ax1, az0, az1) = bounds(a);
        let Some(pa) = Plane::of(a) else { continue };
        for b in t {
            let (bx0, bx1, bz0, bz1) = bounds(b);
            if bx1 < ax0 || bx0 > ax1 || bz1 < az0 || bz0 > az1 {
                continue;
            }
            let Some(pb) = Plane::of(b) else { continue };
            for (x, z) in clip(a, b) {
                worst = worst.max((pa.at(x, z) - pb.at(x, z)).abs());
            }
        }
    }
    worst as f32
}

/// The height over a non-degenerate triangle as a linear function of `(x, z)`.
struct Plane {
    h0: f64,
    dx: f64,
    dz: f64,
    x0: f64,
    z0: f64,
}

impl Plane {
    fn of(t: &[(i64, i64, f32); 3]) -> Option<Plane> {
        let [p0, p1, p2] = t.map(|p| (p.0 as f64, p.1 as f64, p.2 as f64));
        let (ux, uz, uh) = (p1.0 - p0.0, p1.1 - p0.1, p1.2 - p0.2);
        let (vx, vz, vh) = (p2.0 - p0.0, p2.1 - p0.1, p2.2 - p0.2);
        let det = ux * vz - vx * uz;
        if det == 0.0 {
            return None;
        }
        Some(Plane { h0: p0.2, dx: (uh * vz - vh * uz) / det, dz: (ux * vh - vx * uh) / det, x0: p0.0, z0: p0.1 })
    }
    fn at(&self, x: f64, z: f64) -> f64 {
        self.h0 + self.dx * (x - self.x0) + self.dz * (z - self.z0)
    }
}

/// The polygon where triangles `a` and `b` overlap (Sutherland-Hodgman: `a` clipped by
/// each edge of `b`), as its vertices; empty when they do not overlap.
fn clip(a: &[(i64, i64, f32); 3], b: &[(i64, i64, f32); 3]) -> Vec<(f64, f64)> {
    let pts = |t: &[(i64, i64, f32); 3]| t.map(|p| (p.0 as f64, p.1 as f64));
    let mut poly: Vec<(f64, f64)> = pts(a).to_vec();
    let c = pts(b);
    let area = (c[1].0 - c[0].0) * (c[2].1 - c[0].1) - (c[2].0 - c[0].0) * (c[1].1 - c[0].1);
    let sign = area.signum();
    for k in 0..3 {
        let (p, q) = (c[k], c[(k + 1) % 3]);
        // Inside: on the same side of p->q as the triangle's interior (edges included).
        let side = |r: (f64, f64)| sign * ((q.0 - p.0) * (r.1 - p.1) - (q.1 - p.1) * (r.0 - p.0));
        let mut next = Vec::with_capacity(poly.len() + 1);
        for i in 0..poly.len() {
            let (r, s) = (poly[i], poly[(i + 1) % poly.len()]);
            let (sr, ss) = (side(r), side(s));
            if sr >= 0.0 {
                next.push(r);
            }
            if (sr >= 0.0) != (ss >= 0.0) {
                let w = sr / (sr - ss);
                next.push((r.0 + (s.0 - r.0) * w, r.1 + (s.1 - r.1) * w));
            }
        }
        poly = next;
        if poly.is_empty() {
            break;
        }
    }
    poly
}

#[cfg(test)]
mod tests {
    use super::*;

    fn field(side: usize, f: impl Fn(usize, usize) -> f32) -> Heightfield {
        crate::lod::heightfield::test_field(side, side, f)
    }

    /// The height of block `b`'s drawn surface at sample `(x, z)`: the first of its
    /// triangles (collapsed ones cover nothing) that holds the sample.
    fn surface_at(hf: &Heightfield, layout: &BlockLayout, b: &DrawBlock, x: i64, z: i64) -> f32 {
        let last = layout.k() - 1;
        (0..last)
            .flat_map(|v| (0..last).map(move |u| (u, v)))
            .find_map(|(u, v)| {
                let p = |du, dv| block_vertex(hf, layout, b, u + du, v + dv);
                let (a, c, i, g) = (p(0, 0), p(1, 0), p(1, 1), p(0, 1));
                [[a, c, i], [a, i, g]].iter().find_map(|t| crate::lod::geometry::interpolate(t, x, z))
            })
            .expect("the block covers its samples")
    }

    /// The drawn strip departs from the block's own surface by at most `strip_departure`
    /// at every sample of the strip (it is the maximum over the whole row), on a rough
    /// field, at LODs 0 to 3, for coarser neighbours 1 to 3 levels up on each edge; it is
    /// 0 where nothing is stitched and at most the row's vertex range. A measure that
    /// ignored the overlay's crossing points (only the triangles' own corners) misses
    /// the samples' maximum here: the check can fail.
    #[test]
    fn strip_departure_bounds_every_sample_of_the_strip() {
        let hf = field(257, |x, z| (((x * 7919 + z * 104729) % 101) as f32) * 0.37 + ((x + 2 * z) % 5) as f32);
        let layout = BlockLayout::of(&hf, 9).unwrap();
        let (mut checked, mut nonzero) = (0, 0);
        for lod in 0..=3u32 {
            let own = DrawBlock::new(lod, 2, 2);
            assert_eq!(strip_departure(&hf, &layout, &own).edge, [0.0; 4]);
            for up in 1..=3u32 {
                for e in 0..4 {
                    let mut b = own;
                    b.coarser[e] = 1 << (lod + up);
                    let dep = strip_departure(&hf, &layout, &b);
                    let (ox, oz) = b.origin(&layout);
                    let size = layout.block_samples(lod) as i64;
                    let (mut worst, mut range) = (0.0f32, (f32::INFINITY, f32::NEG_INFINITY));
                    for z in oz as i64..=oz as i64 + size {
                        for x in ox as i64..=ox as i64 + size {
                            let (lx, lz) = (x - ox as i64, z - oz as i64);
                            let w = [lz, size - lx, size - lz, lx][e];
                            if w > 1 << lod {
                                continue; // outside the edge's first row
                            }
                            range = (range.0.min(hf.raw_at(x, z)), range.1.max(hf.raw_at(x, z)));
                            let drawn = surface_at(&hf, &layout, &b, x, z);
                            let flat = surface_at(&hf, &layout, &own, x, z);
                            worst = worst.max((drawn - flat).abs());
                            checked += 1;
                        }
                    }
                    assert!(
                        worst <= dep.edge[e] * (1.0 + 1e-5) + 1e-4,
                        "lod {lod} up {up} edge {e}: {worst} > {dep:?}"
                    );
                    assert!(dep.edge[e] <= range.1 - range.0 + 1e-4, "lod {lod} up {up} edge {e}: {dep:?}");
                    nonzero += (dep.edge[e] > 0.0) as usize;
                    for other in (0..4).filter(|&o| o != e && dep.edge[o] > 0.0) {
                        // Only the corner quads of the neighbouring rows can change.
                        assert!(dep.edge[other] <= dep.edge[e] + 1e-4, "lod {lod} edge {e} other {other}: {dep:?}");
                    }
                }
            }
        }
        assert!(checked > 1000 && nonzero >= 40, "{checked} samples, {nonzero} stitched edges measured");
    }

    fn cache_free(hf: &Heightfield, layout: &BlockLayout, b: &DrawBlock) -> StripDeviation {
        StitchCache::default().get(hf, layout, b)
    }

    /// The row scan finds exactly the samples that the barycentric test accepts, for
    /// triangles of every shape and winding (thin, collinear, on negative coordinates).
    #[test]
    fn inside_rows_are_exactly_the_barycentric_samples() {
        let mut seed = 0x2545f4914f6cdd1du64;
        let mut next = |n: i64| {
            seed ^= seed << 13;
            seed ^= seed >> 7;
            seed ^= seed << 17;
            (seed % (2 * n as u64 + 1)) as i64 - n
        };
        let mut tris: Vec<[(i64, i64); 3]> = vec![
            [(0, 0), (8, 0), (8, 8)],
            [(0, 0), (8, 8), (8, 0)],
            [(0, 0), (4, 4), (8, 8)],
            [(3, 3), (3, 3), (3, 3)],
            [(0, 0), (1, 7), (2, 14)],
            [(-5, 2), (9, 3), (-4, 4)],
            [(0, 0), (32, 0), (0, 32)],
        ];
        for _ in 0..3000 {
            let r = if tris.len().is_multiple_of(2) { 3 } else { 40 };
            tris.push([(next(r), next(r)), (next(r), next(r)), (next(r), next(r))]);
        }
        let mut inside = 0;
        for t in &tris {
            let z0 = t.iter().map(|p| p.1).min().unwrap();
            let z1 = t.iter().map(|p| p.1).max().unwrap();
            let x0 = t.iter().map(|p| p.0).min().unwrap();
            let x1 = t.iter().map(|p| p.0).max().unwrap();
            for z in z0 - 1..=z1 + 1 {
                let row = inside_row(*t, z);
                for x in x0 - 1..=x1 + 1 {
                    let want = crate::lod::geometry::barycentric(t, x, z).is_some();
                    assert_eq!(row.contains(&x), want, "{t:?} at ({x}, {z})");
                    inside += want as usize;
                }
            }
        }
        assert!(inside > 10_000, "the triangles cover {inside} samples");
    }

    #[test]
    fn no_coarser_neighbour_costs_nothing() {
        let hf = field(33, |x, z| ((x * 5 + z * 3) % 7) as f32);
        let layout = BlockLayout::of(&hf, 9).unwrap();
        let b = DrawBlock::new(0, 1, 1);
        assert_eq!(cache_free(&hf, &layout, &b).max(), 0.0);
    }

    /// A ridge perpendicular to the north edge, in the first interior row: the collapsed
    /// fan spreads the ridge's height over the strip, which neither block's error covers
    /// (the LOD-0 block has none, the coarse block never sees row 1).
    #[test]
    fn a_ridge_in_the_first_row_shows_in_the_strip() {
        let hf = field(33, |x, z| {
            if z == 8 && x == 3 {
                10.0
            } else if z == 9 && x == 3 {
                50.0
            } else {
                0.0
            }
        });
        let layout = BlockLayout::of(&hf, 9).unwrap();
        // LOD-0 block (0, 1) spans z = 8..16; its north neighbour is coarser (stride 2).
        let b = DrawBlock { coarser: [2, 0, 0, 0], ..DrawBlock::new(0, 0, 1) };
        let d = strip_deviation(&hf, &layout, &b, coarser_sides(&b));
        assert!(d.edge[0] > 0.0 && d.edge[1..] == [0.0; 3], "{d:?}");
        let cache = StitchCache::default();
        assert_eq!(cache.get(&hf, &layout, &b), d);
        assert_eq!(cache.get(&hf, &layout, &b), d);
    }

    /// The regions measured one state at a time, quad by quad (what `edge_regions`
    /// computes with each sample's weights shared across states).
    fn regions_state_by_state(hf: &Heightfield, layout: &BlockLayout, b: &DrawBlock, fixed: u8) -> EdgeRegions {
        use crate::lod::block::MORPH_ONE;
        let last = layout.k() - 2;
        let mut out = EdgeRegions::default();
        let state = |f: bool, edges: &[(usize, bool)]| {
            let q = |on: bool| if on { MORPH_ONE } else { 0 };
            let mut s = DrawBlock { morph: q(f), edge_morph: [MORPH_ONE; 4], ..*b };
            for &(e, on) in edges {
                if fixed & (1 << e) == 0 {
                    s.edge_morph[e] = q(on);
                }
            }
            s
        };
        let range = std::cell::Cell::new((f32::INFINITY, f32::NEG_INFINITY));
        let quad = |s: &DrawBlock, u: u32, v: u32| {
            let vert = |uu: u32, vv: u32| block_vertex(hf, layout, s, uu, vv);
            let (a, c, i, g) = (vert(u, v), vert(u + 1, v), vert(u + 1, v + 1), vert(u, v + 1));
            let (lo, hi) = range.get();
            range.set((
                [a, c, i, g].iter().fold(lo, |l, p| l.min(p.2)),
                [a, c, i, g].iter().fold(hi, |h, p| h.max(p.2)),
            ));
            triangle_deviation(hf, &[a, c, i]).max(triangle_deviation(hf, &[a, i, g]))
        };
        for e in 0..4 {
            for st in 0..4 {
                let s = state(st & 2 != 0, &[(e, st & 1 != 0)]);
                for t in 1..last {
                    let (u, v) = strip_quad(e, t, last);
                    let m = &mut out.side[e][strip_segment(t, last)][st];
                    *m = m.max(quad(&s, u, v));
                }
            }
        }
        for (c, [ea, eb]) in CORNER_EDGES.iter().copied().enumerate() {
            let (u, v) = [(0, 0), (last, 0), (last, last), (0, last)][c];
            for st in 0..8 {
                out.corner[c][st] = quad(&state(st & 4 != 0, &[(ea, st & 2 != 0), (eb, st & 1 != 0)]), u, v);
            }
        }
        (out.lo, out.hi) = range.get();
        out
    }

    /// Rough terrain, a smooth swell (where the cheap bound lets most strip quads be
    /// skipped) and a flat field whose highest vertex sits only in quads that are
    /// skipped (a spike between samples in the segment's first quad, a smaller bump on a
    /// morphing vertex of the LOD-2 block's north strip, three quads on), LODs 1 to 3,
    /// coarser blocks on two sides (collapsed, stitched vertices) and every choice of
    /// fixed edges: every region in every state, and the height range, equal the
    /// state-by-state measure, which skips nothing.
    #[test]
    fn edge_regions_equal_the_state_by_state_measure() {
        let fields = [
            field(257, |x, z| ((x * 7919 + z * 104_729) % 61) as f32 + (x as f32 * 0.3).sin() * 20.0),
            field(257, |x, z| {
                ((x as f32 * 0.05).sin() + (z as f32 * 0.07).cos()) * 40.0 + ((x * 31 + z * 17) % 5) as f32
            }),
            field(257, |x, z| match (x, z) {
                (146, 130) => 50.0,
                (156, 128) => 10.0,
                _ => 0.0,
            }),
        ];
        let (mut skipped, mut nonzero) = (0, 0);
        for hf in &fields {
            let mm = MinMaxPyramid::build(hf);
            // The default block: four quads to a strip segment, so some can be skipped.
            let layout = BlockLayout::of(hf, 33).unwrap();
            for lod in 1..=3u32 {
                let s = 1u32 << lod;
                let at = (256 / layout.block_samples(lod)).min(2) - 1;
                for coarser in [[0, 0, 0, 0], [2 * s, 0, 0, 4 * s], [0, 2 * s, 4 * s, 0]] {
                    let b = DrawBlock { coarser, ..DrawBlock::new(lod, at, at) };
                    for fixed in 0..16u8 {
                        let (got, n) = edge_regions_pruned(hf, &mm, &layout, &b, fixed);
                        let want = regions_state_by_state(hf, &layout, &b, fixed);
                        assert_eq!(got, want, "lod {lod}, coarser {coarser:?}, fixed {fixed:b}");
                        nonzero += got.side.iter().flatten().flatten().any(|&d| d > 0.0) as usize;
                        skipped += n;
                    }
                }
            }
        }
        // Not vacuous: the regions are measured, and the skip is taken.
        assert!(nonzero > 300 && skipped > 100, "{nonzero} nonzero, {skipped} quads skipped");
    }

    /// The cheap bound is an upper bound on the exact regions, component by component, in
    /// every state: LODs 1 to 3 on fields that make each of its two readings tight (rough
    /// noise, a smooth swell with a ridge on the block lines, a lone spike), coarser
    /// blocks across up to two levels up, every choice of fixed edges, and resolved
    /// corners (a corner off its sample, inside a coarser block's edge: there the
    /// parent's surface is not the state-0 one). The factor search relies on it: a cheap term under the exact one lets a
    /// block morph past the bound.
    #[test]
    fn the_cheap_edge_regions_bound_the_exact_ones() {
        let fields = [
            field(129, |x, z| ((x * 7919 + z * 104_729) % 61) as f32 + (x as f32 * 0.3).sin() * 20.0),
            field(129, |x, z| {
                let swell = ((x as f32 * 0.05).sin() + (z as f32 * 0.07).cos()) * 40.0;
                swell + if x % 16 == 0 || z % 16 == 1 { 25.0 } else { 0.0 }
            }),
            field(129, |x, z| if (x, z) == (37, 33) || (x, z) == (49, 47) { 90.0 } else { 0.0 }),
        ];
        let (mut tightened, mut compared) = (0usize, 0usize);
        for hf in &fields {
            let mm = MinMaxPyramid::build(hf);
            let layout = BlockLayout::of(hf, 9).unwrap();
            for lod in 1..=3u32 {
                let per_side = 128 / layout.block_samples(lod);
                let s = 1u32 << lod;
                for (bx, bz) in [(1, 1), (0, per_side - 1), (per_side - 1, 0)] {
                    for coarser in [[0, 0, 0, 0], [2 * s, 0, 0, 4 * s], [0, 4 * s, 2 * s, 0]] {
                        for resolved in [false, true] {
                            let mut b = DrawBlock { coarser, ..DrawBlock::new(lod, bx, bz) };
                            // A corner is off its sample only inside a coarser block's edge.
                            if resolved && coarser != [0; 4] {
                                let (ox, oz) = b.origin(&layout);
                                b.corner_raw[1] = (hf.raw_at((ox + 8 * s) as i64, oz as i64) + 7.0).to_bits();
                                b.corner_raw[3] = (hf.raw_at(ox as i64, (oz + 8 * s) as i64) - 5.0).to_bits();
                            }
                            for fixed in 0..16u8 {
                                let cache = StitchCache::default();
                                let cheap = edge_regions_bound(hf, &mm, &cache, &layout, &b, fixed);
                                let exact = regions_state_by_state(hf, &layout, &b, fixed);
                                let pairs =
                                    cheap.side.iter().flatten().flatten().zip(exact.side.iter().flatten().flatten());
                                let corners = cheap.corner.iter().flatten().zip(exact.corner.iter().flatten());
                                let all: Vec<(&f32, &f32)> = pairs.chain(corners).collect();
                                assert_eq!(all.len(), 4 * STRIP_SEGMENTS * 4 + 4 * 8);
                                for (c, x) in all {
                                    let slack = 1e-4 * x.abs().max(1.0);
                                    assert!(
                                        *c + slack >= *x,
                                        "cheap {c} under exact {x}: lod {lod}, block ({bx}, {bz}), coarser {coarser:?}, fixed {fixed:04b}, resolved {resolved}"
                                    );
                                    compared += 1;
                                    tightened += (*c <= *x + slack) as usize;
                                }
                            }
                        }
                    }
                }
            }
        }
        // Not vacuous: somewhere the cheap bound is the exact value.
        assert!(tightened > 0 && compared > 100_000, "{tightened} of {compared}");
    }
}
