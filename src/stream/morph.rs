//! Geomorphing of streamed frames, paid for inside the bound (SPEC section 3: "anything
//! that changes the drawn surface adds its own term"), from what the held tiles know: the
//! blocks' square summaries and the parent LOD's `D` of each group.
//!
//! A streamed block's interior vertices move from its parent's surface (factor 0) to
//! their own samples (factor 1), as in memory ([`crate::lod::morph`]), and so do the
//! vertices of an edge shared with a drawn block of the same LOD, with one factor for the
//! edge (the larger of the two blocks', so both draw the same vertices). Every other edge
//! (next to a coarser or finer block, or with no drawn block across) and every corner stay
//! on their samples: watertight as unmorphed frames are, with no factor shared beyond two
//! blocks.
//!
//! The bound, per square of the block (its `4 x 4` quads, its own box and distance, as
//! the selection's [`super::traverse`] bounds them), for interior factor `f` and edge
//! factors at least `f`:
//! - a quad off the block's first row along every edge has all its vertices at `f`, so
//!   the drawn surface is `(1 - f) S0 + f S1` and deviates from the samples by at most
//!   `(1 - f) E0 + f E1`: `E0` the largest `D_{j+1}` of the square's parent groups (`S0`
//!   is the parent's surface there: the child quads split along the same diagonal), `E1`
//!   the square's `D_j`;
//! - a quad of the first row (the strip, stitched or not) deviates from the samples by at
//!   most its unmorphed deviation (the square's `D_j`, or along a coarser neighbour the
//!   edge row's `D_j` plus the strip's departure) plus `(1 - f) E0`: each vertex moves by
//!   `1 - factor` of its distance from the parent's surface, and a vertex is a sample of
//!   a parent group that contains it, which deviates from that surface by at most the
//!   group's `D_{j+1}` (edges included). Along an edge next to a coarser block the
//!   stitched fan triangles reach across squares, so there the move and the heights are
//!   the whole edge's largest (an adversarial review's field audited at 5.95 px before).
//!
//! Both are affine in `f`; the factor is the least multiple of 1/64, at least the ramp
//! ([`MORPH_RANGE`], as in memory), that keeps every term within delta, else 1 (the
//! selection's own surface, which it bounds). The frames differ from the in-memory ones
//! only in the factors: the in-memory bound measures each group from its own box and the
//! edge regions exactly, which the tiles do not hold.

use super::cache::{layout, root_lod, serving_tile, HostCache, Resident, SUB};
use super::traverse::{block_box, square_box, Selection, StripCache, View};
use super::Grid;
use crate::lod::block::{map_in_pool, morph_value, DrawBlock, MORPH_ONE};
use crate::lod::camera::{angular_factor, distance_to_aabb, Camera};
use crate::lod::morph::{MorphRule, MORPH_RANGE};
use crate::lod::stitch::{coarser_sides, strip_departure};
use foldhash::{HashMap, HashMapExt};

/// Steps of the factor (as in memory).
const STEP: u16 = MORPH_ONE / 64;

/// Terms `a + b f` (pixels) whose maximum bounds a block's error at interior factor `f`,
/// and the parent's error (every vertex at 0) for the ramp.
#[derive(Clone, Debug, Default)]
pub struct MorphTerms {
    terms: Vec<(f32, f32)>,
    parent_px: f32,
}

impl MorphTerms {
    /// The bound at factor `f` (edges at `f` or above).
    pub fn bound(&self, f: f32) -> f32 {
        self.terms.iter().map(|&(a, b)| a + b * f).fold(0.0, f32::max)
    }

    /// The least factor (a multiple of [`STEP`], at least `from`) whose bound is within
    /// `delta`; [`MORPH_ONE`] when none below it is.
    fn least_factor(&self, from: u16, delta: f32) -> u16 {
        if self.bound(morph_value(from)) <= delta {
            return from;
        }
        // Each term caps or floors `f`: solve for the floor, then step up from there,
        // checking in the units the shader gets.
        let (mut lo, mut hi) = (morph_value(from), 1.0f32);
        for &(a, b) in &self.terms {
            if b < 0.0 {
                lo = lo.max((a - delta) / -b);
            } else if b > 0.0 {
                hi = hi.min((delta - a) / b);
            } else if a > delta {
                return MORPH_ONE;
            }
        }
        if lo.is_nan() || lo > hi || lo >= 1.0 {
            return MORPH_ONE;
        }
        // The multiple of STEP below the floor too: the floor is rounded.
        let mut q = (((lo * MORPH_ONE as f32 / STEP as f32).floor() as u16).saturating_sub(1) * STEP).max(from);
        while q < MORPH_ONE && self.bound(morph_value(q)) > delta {
            q = (q + STEP - q % STEP).min(MORPH_ONE);
        }
        q
    }
}

/// The terms of block `b` (as drawn: stitched, unmorphed) of the selection, for `cam`
/// relative to sample `anchor` ([`View::relative`]); `None` for a block that does not
/// morph (a root, or its tiles not held).
pub fn terms(
    grid: &Grid,
    cache: &HostCache,
    strips: &StripCache,
    (anchor, cam): ([i64; 2], &Camera),
    delta: f32,
    b: &DrawBlock,
) -> Option<MorphTerms> {
    let (j, bx, bz) = (b.lod, b.bx, b.bz);
    if j >= root_lod(grid) {
        return None;
    }
    let s = cache.peek(serving_tile(grid, j, bx, bz))?.block(grid, j, bx, bz);
    let parent = cache.peek(serving_tile(grid, j + 1, bx / 2, bz / 2))?;
    let l = layout(grid);
    let dep = (coarser_sides(b) != 0)
        .then(|| strips.get_or_compute(b.unmorphed(), || strip_departure(&Resident { grid, cache }, &l, b)));
    let (lo, hi) = dep.map_or((s.min, s.max), |d| (s.min.min(d.lo), s.max.max(d.hi)));
    let boxed = block_box(grid, anchor, j, bx, bz, lo, hi);
    let scale = grid.height_scale as f32;
    let per_distance = scale * cam.kappa() * angular_factor(cam, boxed.0, boxed.1, delta);
    // The block's parent groups (LOD j + 1): block_quads / 2 a side from here.
    let quads = grid.block_quads;
    let (gx0, gz0) = (bx as usize * quads / 2, bz as usize * quads / 2);
    // A square is `q` quads a side; its parent groups are those its quads lie in (one
    // group for half of it when a square is a single quad, as with blocks of k = 9).
    let q = quads / SUB;
    let groups = |s: usize| s * q / 2..((s + 1) * q).div_ceil(2);
    let mut out = MorphTerms { terms: Vec::with_capacity(2 * SUB * SUB), parent_px: 0.0 };
    let e0_of = |sx: usize, sz: usize| {
        let mut e0 = 0.0f32;
        for gz in groups(sz).map(|g| gz0 + g) {
            for gx in groups(sx).map(|g| gx0 + g) {
                e0 = e0.max(parent.group_d(grid, j + 1, gx, gz));
            }
        }
        e0
    };
    let e0: Vec<f32> = (0..SUB * SUB).map(|i| e0_of(i % SUB, i / SUB)).collect();
    // Along an edge next to a coarser block, a fan triangle of the stitched strip spans
    // up to the neighbour's segment, so a sample's drawn height there interpolates the
    // moved row-1 vertices of other squares along the edge: the strip is paid with the
    // largest move, and the heights, of the whole edge's squares.
    let on_edge = |e: usize, k: usize| match e {
        0 => k,
        1 => k * SUB + SUB - 1,
        2 => (SUB - 1) * SUB + k,
        _ => k * SUB,
    };
    let edge_wide: [(f32, f32, f32); 4] = std::array::from_fn(|e| {
        (0..SUB).map(|k| on_edge(e, k)).fold((0.0f32, f32::INFINITY, f32::NEG_INFINITY), |(m, lo, hi), i| {
            (m.max(e0[i]), lo.min(s.squares[i].min), hi.max(s.squares[i].max))
        })
    });
    for sz in 0..SUB {
        for sx in 0..SUB {
            let sq = &s.squares[sz * SUB + sx];
            let e0_own = e0[sz * SUB + sx];
            // The edges this square lies along, and its place on each.
            let along = [(sz == 0, sx), (sx == SUB - 1, sz), (sz == SUB - 1, sx), (sx == 0, sz)];
            let (mut ylo, mut yhi) = (sq.min, sq.max);
            let (mut strip, mut e0_strip) = (sq.d, e0_own);
            for (e, &(on, k)) in along.iter().enumerate() {
                if let Some(d) = dep.filter(|_| on && b.coarser[e] > 0) {
                    let (m, lo, hi) = edge_wide[e];
                    (ylo, yhi) = (ylo.min(d.lo).min(lo), yhi.max(d.hi).max(hi));
                    strip = strip.max(s.edge_d[e][k] + d.edge[e]);
                    e0_strip = e0_strip.max(m);
                }
            }
            let (min, max) = square_box(grid.height_scale, boxed, sx, sz, ylo, yhi);
            let px = per_distance / distance_to_aabb(cam.position, min, max).max(cam.near);
            out.terms.push((e0_own * px, (sq.d - e0_own) * px));
            if along.iter().any(|a| a.0) {
                out.terms.push(((strip + e0_strip) * px, -e0_strip * px));
            }
            out.parent_px = out.parent_px.max(e0_own * px);
        }
    }
    Some(out)
}

/// Sets the morph factors of the selection's drawn blocks (`sel.stitched`) for `view` by
/// `rule` ([`MorphRule::Bounded`] is the renderer's; the others break it on purpose for
/// the tests); returns how many blocks morph. Blocks over the bound stay on their samples.
pub fn assign(
    grid: &Grid,
    cache: &HostCache,
    strips: &StripCache,
    view: &View,
    delta: f32,
    sel: &mut Selection,
    rule: MorphRule,
) -> usize {
    if sel.stitched.len() != sel.blocks.len() {
        return 0; // a selection made without the stitching rule is not drawn
    }
    let (anchor, cam) = view.relative(grid);
    // Each block's terms on every thread of the caller's pool (`--traversal-threads`):
    // the same factors in the same order on any number.
    let q: Vec<u16> = map_in_pool(&sel.stitched, |i, b| {
        if sel.blocks[i].over {
            return MORPH_ONE;
        }
        let Some(t) = terms(grid, cache, strips, (anchor, &cam), delta, b) else { return MORPH_ONE };
        let ramp = ((t.parent_px / delta - 1.0) / (MORPH_RANGE - 1.0)).clamp(0.0, 1.0);
        let from = (ramp * MORPH_ONE as f32).ceil() as u16;
        match rule {
            MorphRule::ParentSurface => 0,
            MorphRule::Underpaid => t.least_factor(from, delta) / 2,
            MorphRule::Bounded | MorphRule::BoundedLazy => t.least_factor(from, delta),
        }
    });
    let index: HashMap<(u32, u32, u32), usize> = {
        let mut m = HashMap::with_capacity(sel.stitched.len());
        for (i, b) in sel.stitched.iter().enumerate() {
            m.insert((b.lod, b.bx, b.bz), i);
        }
        m
    };
    let mut morphing = 0;
    for i in 0..sel.stitched.len() {
        let b = sel.stitched[i];
        let across = |s: usize| -> Option<usize> {
            let (x, z) = match s {
                0 => (Some(b.bx), b.bz.checked_sub(1)),
                1 => (b.bx.checked_add(1), Some(b.bz)),
                2 => (Some(b.bx), b.bz.checked_add(1)),
                _ => (b.bx.checked_sub(1), Some(b.bz)),
            };
            index.get(&(b.lod, x?, z?)).copied()
        };
        let edges: [u16; 4] = std::array::from_fn(|s| match across(s) {
            // Both blocks give the edge the larger factor: it is at least each one's own.
            Some(n) if b.coarser[s] == 0 => q[i].max(q[n]),
            _ => MORPH_ONE,
        });
        let d = &mut sel.stitched[i];
        d.morph = q[i];
        d.edge_morph = edges;
        morphing += usize::from(q[i] < MORPH_ONE || edges.iter().any(|&e| e < MORPH_ONE));
    }
    morphing
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Against a search over every factor: the factor chosen meets delta (or is 1), is at
    /// least where it starts, and is the first that does (where it starts, or a multiple
    /// of the step). Found a start between steps rounded past the only factors allowed.
    #[test]
    fn the_least_factor_is_the_searched_one() {
        let mut state = 0x2545_f491_4f6c_dd1d_u64;
        let mut rnd = || {
            state ^= state << 13;
            state ^= state >> 7;
            state ^= state << 17;
            (state >> 11) as f32 / (1u64 << 53) as f32
        };
        let (mut inside, mut raised) = (0, 0);
        for _ in 0..20_000 {
            let n = 1 + (rnd() * 6.0) as usize;
            let terms = (0..n).map(|_| (rnd() * 3.0, (rnd() - 0.6) * 4.0)).collect();
            let t = MorphTerms { terms, parent_px: 0.0 };
            let (from, delta) = ((rnd() * MORPH_ONE as f32) as u16, 0.5 + rnd());
            let q = t.least_factor(from, delta);
            assert!(q >= from && q <= MORPH_ONE);
            assert!(q == MORPH_ONE || t.bound(morph_value(q)) <= delta, "{t:?} from {from}: {q}");
            let candidates = std::iter::once(from).chain((0..=MORPH_ONE).step_by(STEP as usize).filter(|&m| m > from));
            let searched = candidates.into_iter().find(|&m| t.bound(morph_value(m)) <= delta).unwrap_or(MORPH_ONE);
            assert_eq!(q, searched, "{t:?} from {from}");
            inside += usize::from(q < MORPH_ONE);
            raised += usize::from(q > from && q < MORPH_ONE);
        }
        assert!(inside > 2_000 && raised > 1_000, "{inside} within, {raised} raised");
    }
}
