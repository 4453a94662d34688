//! Geomorphing inside the bound (SPEC section 3: "anything that changes the drawn surface
//! adds its own term"). A block's odd vertices move from its parent's surface (factor 0)
//! to their own samples (factor 1); a block that has just split starts on its parent's
//! surface, and one about to split is on its own, so its surface does not jump.
//!
//! Which vertices morph, so that the surface stays watertight:
//! - interior vertices, with the block's factor `f`;
//! - vertices on an edge shared with a block of the same LOD, with one factor for the
//!   edge: the larger of the two blocks' (no other block touches them);
//! - not the vertices on an edge next to a coarser or finer block (factor 1). Their
//!   corners and collapsed vertices are shared with a third block that does not know the
//!   others' factors; unmorphed, every block computes the same height, as before.
//!
//! The factor is chosen per frame, as small as the bound allows:
//! - With the edge vertices next to other LODs fixed and every other vertex at one
//!   factor `f`, the surface is affine in `f` (the triangulation does not move), so its
//!   deviation is at most `(1 - f) E0 + f E1`, the two ends measured exactly:
//!   - away from the fixed edges, per parent group with that group's distance, as the
//!     errors activity does: `E0` from `D_{j+1}`, `E1` from the largest `D_j` of the
//!     group's four children;
//!   - in the first row of quads along the fixed edges, the exact strip deviations
//!     (`stitch.rs`) with the free vertices at 0 and at 1.
//! - A same-LOD edge's factor `e` may exceed `f`: its vertices then move the surface by at
//!   most `(e - f) |h1 - h0|`, with `h1 - h0` a vertex's whole morph. That is added.
//! - At the moment a block splits its parent's error is delta, so `E0 <= delta` and
//!   `f = 0` fits, unless a fixed edge's strip does not.
//! - Factors only rise, to the least value that meets the bound given the neighbours'
//!   edges, until nothing changes. Factor 1 everywhere is the selection's own surface,
//!   which the selection already bounds, so that fallback is always sound.
//!
//! Pixels per world unit of a group: `kappa * a_b / dist(group box)`, with `a_b` the
//! block's angular factor ([`crate::quadtree::angular_factor`]); the morphed surface lies
//! between the parent's and the own surface, inside the group's box. Computed fresh for
//! this frame's camera, so stale error data plays no part here.

use crate::camera::{distance_to_aabb, Camera};
use crate::heightfield::{Heightfield, MinMaxPyramid};
use crate::quadtree::{
    angular_factor, block_aabb, morph_value, world_to_pixels, BlockLayout, DrawBlock, MorphState, Traversal, MORPH_ONE,
};
use glam::Vec3;
use std::collections::HashMap;

/// What a block's morph costs, in pixels for this frame's camera.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct MorphCost {
    /// Bound on the error away from the fixed edges, every free vertex at factor 0.
    pub parent: f32,
    /// The same with every vertex at factor 1.
    pub own: f32,
    /// Strips along the fixed edges (next to another LOD), free vertices at 0 and at 1.
    pub strip_parent: f32,
    pub strip_own: f32,
    /// Largest whole morph `|h1 - h0|` of a vertex on each edge (north, east, south, west).
    pub edge_move: [f32; 4],
    /// Edges whose vertices do not morph (bit `e` for edge `e`).
    pub fixed: u8,
}

impl MorphCost {
    /// Bound on the block's error with interior factor `f` and edge factors `e`.
    pub fn bound(&self, f: f32, e: [f32; 4]) -> f32 {
        let base = ((1.0 - f) * self.parent + f * self.own).max((1.0 - f) * self.strip_parent + f * self.strip_own);
        let free = |s: &usize| self.fixed & (1 << s) == 0;
        base + (0..4).filter(free).map(|s| (e[s] - f).abs() * self.edge_move[s]).fold(0.0, f32::max)
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
}

/// The morph's cost for block `b` (with its neighbours' strides set) whose edges in
/// `fixed` do not morph.
pub fn cost(
    hf: &Heightfield,
    mm: &MinMaxPyramid,
    layout: &BlockLayout,
    cam: &Camera,
    delta: f32,
    b: &DrawBlock,
    fixed: u8,
) -> MorphCost {
    let hs = hf.height_scale;
    let j = b.lod;
    let own_state = b.in_state(MorphState::Own);
    let mut parent_state = b.in_state(MorphState::Parent);
    for (s, e) in parent_state.edge_morph.iter_mut().enumerate() {
        if fixed & (1 << s) != 0 {
            *e = MORPH_ONE;
        }
    }
    let strips = (fixed != 0)
        .then(|| (mm.stitch.strips(hf, layout, &parent_state, fixed), mm.stitch.strips(hf, layout, &own_state, fixed)));
    let (mut min, mut max) = block_aabb(hf, mm, layout, j, b.bx, b.bz);
    if let Some((p, o)) = &strips {
        min.y = min.y.min(p.lo.min(o.lo) * hs);
        max.y = max.y.max(p.hi.max(o.hi) * hs);
    }
    let px = world_to_pixels(cam, min, max, delta);
    let per_group = cam.kappa() * angular_factor(cam, min, max, delta);

    // Away from the fixed edges: per parent group (level j + 1), as the errors activity
    // projects.
    let level = j + 1;
    let gs = 1usize << level;
    let per_side = (layout.k() as usize - 1) / 2;
    let (ox, oz) = b.origin(layout);
    let (ga, gb) = (ox as usize / gs, oz as usize / gs);
    let side = mm.cells(level);
    let world = gs as f32 * hf.spacing;
    let (mut parent, mut own) = (0.0f32, 0.0f32);
    for gz in gb..(gb + per_side).min(side) {
        for gx in ga..(ga + per_side).min(side) {
            let d0 = mm.deviation(level, gx, gz);
            let dc = if j == 0 {
                0.0
            } else {
                let mut m = 0.0f32;
                for (cx, cz) in [(0, 0), (1, 0), (0, 1), (1, 1)] {
                    m = m.max(mm.deviation(j, 2 * gx + cx, 2 * gz + cz));
                }
                m
            };
            if d0 == 0.0 && dc == 0.0 {
                continue;
            }
            let [lo, hi] = mm.get(level, gx, gz);
            let gmin = Vec3::new(gx as f32 * world, lo * hs, gz as f32 * world);
            let gmax = Vec3::new((gx + 1) as f32 * world, hi * hs, (gz + 1) as f32 * world);
            let f = per_group / distance_to_aabb(cam.position, gmin, gmax).max(cam.near);
            parent = parent.max(d0 * hs * f);
            own = own.max(dc * hs * f);
        }
    }
    let (strip_parent, strip_own) = strips.map_or((0.0, 0.0), |(p, o)| (p.max() * hs * px, o.max() * hs * px));

    // Free edges: each odd vertex's whole morph, from the mean of its neighbours along
    // the edge to its own sample (fixed edges do not morph).
    let k = layout.k() as i64;
    let stride = b.stride() as i64;
    let mut edge_move = [0.0f32; 4];
    for (s, m) in edge_move.iter_mut().enumerate() {
        if fixed & (1 << s) != 0 {
            continue;
        }
        let ((x0, z0), (dx, dz)) = match s {
            0 => ((0, 0), (1, 0)),
            1 => ((k - 1, 0), (0, 1)),
            2 => ((0, k - 1), (1, 0)),
            _ => ((0, 0), (0, 1)),
        };
        for t in (1..k - 1).step_by(2) {
            let (x, z) = (ox as i64 + (x0 + t * dx) * stride, oz as i64 + (z0 + t * dz) * stride);
            let mean =
                (hf.raw_at(x - dx * stride, z - dz * stride) + hf.raw_at(x + dx * stride, z + dz * stride)) * 0.5;
            *m = m.max((hf.raw_at(x, z) - mean).abs() * hs * px);
        }
    }
    MorphCost { parent, own, strip_parent, strip_own, edge_move, fixed }
}

/// The least factor `>= current` (in steps of `1 / MORPH_ONE`) that meets `delta` with
/// these edge factors, or `MORPH_ONE` (always sound) when none does.
fn least_factor(c: &MorphCost, current: u16, edges: [u16; 4], delta: f32) -> u16 {
    let e = edges.map(morph_value);
    // Edge factors below `f` rise to `f` with it (they are maxima), so they cost nothing.
    let fits = |f: f32| c.bound(f, e.map(|x| x.max(f))) <= delta;
    // The feasible set is a union of intervals whose left ends are where a constraint
    // line meets delta, or an edge factor.
    let mut lines = Vec::new();
    for (a, b) in [(c.parent, c.own), (c.strip_parent, c.strip_own)] {
        lines.push((a, b - a));
        for (s, (&es, &d)) in e.iter().zip(&c.edge_move).enumerate() {
            if c.fixed & (1 << s) == 0 {
                lines.push((a + es * d, b - a - d));
            }
        }
    }
    let mut candidates: Vec<f32> = vec![morph_value(current)];
    candidates.extend(lines.iter().filter(|l| l.1 != 0.0).map(|&(a, b)| (delta - a) / b));
    candidates.extend(e);
    candidates.retain(|f| f.is_finite() && *f >= morph_value(current) && *f <= 1.0);
    candidates.sort_by(f32::total_cmp);
    for f in candidates {
        let q = ((f * MORPH_ONE as f32).ceil() as u16).clamp(current, MORPH_ONE);
        if fits(morph_value(q)) {
            return q;
        }
    }
    MORPH_ONE
}

/// A block reaches its own surface at the latest when its parent's error is this many
/// times delta (linearly from its split, where the parent's error is delta); before, if the
/// bound asks for it. Without it a block would sit at exactly delta until it splits.
pub const MORPH_RANGE: f32 = 2.0;

/// Rounds of raising before giving up on morphing this frame (factor 1 everywhere).
const MAX_ROUNDS: usize = 200;

/// Sets every block's morph factors (the renderer's rule).
pub fn assign(hf: &Heightfield, mm: &MinMaxPyramid, layout: &BlockLayout, cam: &Camera, delta: f32, t: &mut Traversal) {
    assign_with(hf, mm, layout, cam, delta, t, MorphRule::Bounded);
}

/// Sets every block's morph factors by `rule`.
pub fn assign_with(
    hf: &Heightfield,
    mm: &MinMaxPyramid,
    layout: &BlockLayout,
    cam: &Camera,
    delta: f32,
    t: &mut Traversal,
    rule: MorphRule,
) {
    let root = layout.root_lod();
    let n = t.blocks.len();
    let index: HashMap<(u32, u32, u32), usize> =
        t.blocks.iter().enumerate().map(|(i, b)| ((b.lod, b.bx, b.bz), i)).collect();
    let cells = layout.cells() as i64;
    // Across each edge: the same-LOD neighbour, or a block of another LOD (fixed edge).
    let mut same = vec![[None; 4]; n];
    let mut fixed = vec![0u8; n];
    for (i, b) in t.blocks.iter().enumerate() {
        let span = 1i64 << b.lod;
        let (cx, cz) = (b.bx as i64 * span, b.bz as i64 * span);
        for (s, (nx, nz)) in [(cx, cz - 1), (cx + span, cz), (cx, cz + span), (cx - 1, cz)].into_iter().enumerate() {
            if nx < 0 || nz < 0 || nx >= cells || nz >= cells {
                continue;
            }
            let l = t.lod_map[(nz * cells + nx) as usize];
            if l == b.lod as i8 {
                let l = l as u32;
                same[i][s] = index.get(&(l, (nx >> l) as u32, (nz >> l) as u32)).copied();
                continue;
            }
            // Finer blocks, some perhaps culled, may line the edge: any drawn one fixes it.
            let (dx, dz) = if s % 2 == 0 { (1, 0) } else { (0, 1) };
            if (0..span).any(|d| t.lod_map[((nz + d * dz) * cells + nx + d * dx) as usize] >= 0) {
                fixed[i] |= 1 << s;
            }
        }
    }
    // The root has no parent to morph from.
    let costs: Vec<Option<MorphCost>> = t
        .blocks
        .iter()
        .zip(&fixed)
        .map(|(b, &fx)| (b.lod < root).then(|| cost(hf, mm, layout, cam, delta, b, fx)))
        .collect();
    // Start from the ramp; the bound may ask for more.
    let mut q: Vec<u16> = costs
        .iter()
        .map(|c| match c {
            Some(_) if rule == MorphRule::ParentSurface => 0,
            Some(c) => {
                let f = ((c.parent / delta - 1.0) / (MORPH_RANGE - 1.0)).clamp(0.0, 1.0);
                (f * MORPH_ONE as f32).ceil() as u16
            }
            None => MORPH_ONE,
        })
        .collect();
    let mut edges = vec![[MORPH_ONE; 4]; n];
    let mut settled = false;
    for _ in 0..MAX_ROUNDS {
        for i in 0..n {
            for s in 0..4 {
                edges[i][s] =
                    if fixed[i] & (1 << s) != 0 { MORPH_ONE } else { same[i][s].map_or(q[i], |m| q[i].max(q[m])) };
            }
        }
        if rule == MorphRule::ParentSurface {
            settled = true;
            break;
        }
        let mut changed = false;
        for i in 0..n {
            if let Some(c) = &costs[i] {
                let need = least_factor(c, q[i], edges[i], delta);
                if need > q[i] {
                    q[i] = need;
                    changed = true;
                }
            }
        }
        if !changed {
            settled = true;
            break;
        }
    }
    if !settled {
        q.fill(MORPH_ONE);
        edges.fill([MORPH_ONE; 4]);
    }
    if rule == MorphRule::Underpaid {
        for f in q.iter_mut().chain(edges.iter_mut().flatten()) {
            *f /= 2;
        }
    }
    t.morphing = 0;
    for (i, b) in t.blocks.iter_mut().enumerate() {
        b.morph = q[i];
        b.edge_morph = edges[i];
        if q[i] < MORPH_ONE || edges[i].iter().any(|&e| e < MORPH_ONE) {
            t.morphing += 1;
            if let Some(c) = &costs[i] {
                t.max_block_error = t.max_block_error.max(c.bound(morph_value(q[i]), edges[i].map(morph_value)));
            }
        }
    }
}
