//! Streaming from a tile archive (issue 27 items 3-5, SPEC section 8), host side: the
//! tiles' block summaries against the full-resolution oracle, the bound and the audit on
//! settled frames, honest counting when the cache is too small to hold what a frame
//! needs, the cache's invariants under random use, a damaged archive degrading, and the
//! same frames 1e7 and 1e8 units from the origin.

mod common;

use common::{cli, TempDir};
use glam::DVec3;
use std::sync::Arc;
use vkterrain::input::archive::Archive;
use vkterrain::lod::audit::{audit_block, check_tiling};
use vkterrain::lod::block::{block_vertex, BlockLayout, DrawBlock};
use vkterrain::lod::camera::Camera;
use vkterrain::lod::deviation::exact_deviation;
use vkterrain::lod::heightfield::Heightfield;
use vkterrain::lod::heightfield::RawSamples;
use vkterrain::lod::pyramid::MinMaxPyramid;
use vkterrain::lod::traversal::stitch_selection;
use vkterrain::stream::cache::{root_lod, serving_tile, Heights, HostCache, Refused, Square, TileData, SUB};
use vkterrain::stream::io::TileSource;
use vkterrain::stream::streamer::{Streamer, RETRY_FRAMES};
use vkterrain::stream::traverse::{select, Selection, View};
use vkterrain::stream::{draw, Grid, TileKey};

const DELTA: f32 = 1.0;

/// The rough field, its archive in a temporary directory (removed with it) and its grid.
struct Fixture {
    hf: Heightfield,
    archive: Arc<Archive>,
    grid: Grid,
    _dir: TempDir,
}

fn fixture(tag: &str) -> Fixture {
    let hf = common::rough();
    let dir = TempDir::new(tag);
    let archive = common::archive_of(&hf, &dir);
    let grid = Grid::from_meta(&archive.meta);
    Fixture { hf, archive, grid, _dir: dir }
}

/// Low views toward the horizon, views down, views from outside the terrain looking in.
/// Positions are multiples of 1/16, so that moved 1e8 away they stay exact in f64.
fn poses() -> Vec<View> {
    let q = |p: DVec3| (p * 16.0).round() / 16.0;
    let mut v = Vec::new();
    for i in 0..12 {
        let a = i as f64 * std::f64::consts::TAU / 12.0;
        let p = DVec3::new(1500.0 + 700.0 * a.cos(), 160.0 + 40.0 * (i % 3) as f64, 2500.0 + 1200.0 * a.sin());
        let t = p + DVec3::new(-a.sin() * 1000.0, -60.0, a.cos() * 1000.0);
        v.push(View::look_at(q(p), t, 45.0, 320, 240, 1.0));
    }
    v.push(View::look_at(DVec3::new(1536.0, 1500.0, 2560.0), DVec3::new(1540.0, 0.0, 2500.0), 60.0, 320, 240, 1.0));
    v.push(View::look_at(DVec3::new(-400.0, 300.0, -300.0), DVec3::new(1500.0, 0.0, 2500.0), 45.0, 320, 240, 1.0));
    v.push(View::look_at(
        DVec3::new(2100.0, 180.0, 1666.0),
        DVec3::new(2100.0, 900.0, 1666.0 + 1.0),
        45.0,
        320,
        240,
        1.0,
    ));
    v
}

/// The view as the in-memory code sees it (sample (0, 0) at the world's origin).
fn camera(view: &View) -> Camera {
    view.absolute()
}

/// Frames at `view` until every tile the selection wants is held (or `limit` frames).
fn settled(s: &mut Streamer, view: &View, limit: usize) -> Selection {
    for _ in 0..limit {
        let sel = s.frame(view, None, DELTA, 1.0);
        if sel.within_bound() {
            return sel;
        }
        s.settle();
    }
    panic!("not settled after {limit} frames");
}

/// For blocks of the paper's k = 33, the smallest and the largest a tile of 256 quads
/// takes (`--block`).
#[test]
fn tile_summaries_equal_the_full_resolution_oracle() {
    let Fixture { hf, archive, grid, _dir } = fixture("stream-summaries");
    let d = exact_deviation(&hf);
    for k in [33, 9, 129] {
        let grid = grid.with_block(k).unwrap();
        summaries_equal_the_oracle(&hf, &d, &archive, &grid);
    }
    for k in [5, 10, 257, 513] {
        let e = grid.with_block(k).unwrap_err();
        assert!(e.contains("blocks of 9, 17, 33, 65, 129 vertices"), "--block {k}: {e}");
    }
}

fn summaries_equal_the_oracle(hf: &Heightfield, d: &[Vec<f32>], archive: &Archive, grid: &Grid) {
    let (grid, quads) = (*grid, grid.block_quads);
    // Root blocks of LOD 5 for k = 33.
    let root = 2 + (256 / quads).trailing_zeros();
    assert_eq!((grid.top, root_lod(&grid)), (2, root), "a 1025^2 terrain: three tile levels");
    let (mut checked, mut groups_checked) = (0, 0usize);
    for (level, tx, tz) in archive.meta.tiles() {
        let tile = archive.read_tile(level, tx, tz).unwrap().unwrap();
        let data = TileData::new(&grid, tile.clone()).unwrap();
        // Heights that are 16-bit integers (a 16-bit source) are held in 16 bits, exactly;
        // fractional ones (this float field) stay floats.
        assert!(matches!(data.heights, Heights::Float32(_)), "tile {level}/{tx}/{tz} of a float field");
        let mut whole = tile.clone();
        whole.heights.iter_mut().for_each(|h| *h = h.round().clamp(0.0, 65535.0));
        let narrow = TileData::new(&grid, whole.clone()).unwrap();
        assert!(matches!(narrow.heights, Heights::Unorm16(_)));
        let n = tile.vertices();
        for (i, j) in (0..n).flat_map(|j| (0..n).map(move |i| (i, j))) {
            assert_eq!(data.vertex(i, j), tile.heights[(j + 1) * tile.side + i + 1]);
            assert_eq!(narrow.vertex(i, j), whole.heights[(j + 1) * tile.side + i + 1]);
        }
        assert_eq!(data.bytes - narrow.bytes, tile.heights.len() * 2);
        let last = if level == grid.top { root_lod(&grid) } else { u32::from(level) };
        for lod in u32::from(level)..=last {
            let per = ((grid.tile_quads << level) / (quads << lod)) as u32;
            for (bx, bz) in (0..per).flat_map(|z| (0..per).map(move |x| (tx * per + x, tz * per + z))) {
                assert_eq!(serving_tile(&grid, lod, bx, bz), TileKey::new(level, tx, tz));
                let (size, stride) = ((quads << lod) as i64, 1i64 << lod);
                let (ox, oz) = (i64::from(bx) * size, i64::from(bz) * size);
                let (mut lo, mut hi) = (f32::INFINITY, f32::NEG_INFINITY);
                for z in (oz..=oz + size).step_by(stride as usize) {
                    for x in (ox..=ox + size).step_by(stride as usize) {
                        lo = lo.min(hf.raw_at(x, z));
                        hi = hi.max(hf.raw_at(x, z));
                    }
                }
                // D of the whole block and of each of its SUB x SUB squares, from the
                // in-memory deviations, and each square's heights: its groups' corners
                // widened by the group's D.
                let q = quads / SUB;
                let mut dmax = 0.0f32;
                let mut squares = [Square { d: 0.0, min: f32::INFINITY, max: f32::NEG_INFINITY }; SUB * SUB];
                // The edges' rows of groups (north, east, south, west), square by square.
                let mut edge_d = [[0.0f32; SUB]; 4];
                for (gx, gz) in (0..quads).flat_map(|z| (0..quads).map(move |x| (x, z))) {
                    let (cx, cz) = (ox + gx as i64 * stride, oz + gz as i64 * stride);
                    let c = [(0, 0), (1, 0), (0, 1), (1, 1)].map(|(u, v)| hf.raw_at(cx + u * stride, cz + v * stride));
                    let cells = hf.cells(lod.max(1))[0];
                    let g = if lod > 0 {
                        d[lod as usize - 1][(bz as usize * quads + gz) * cells + bx as usize * quads + gx]
                    } else {
                        0.0
                    };
                    let sq = &mut squares[gz / q * SUB + gx / q];
                    sq.d = sq.d.max(g);
                    let last = quads - 1;
                    for (e, k, on) in [(0, gx, gz == 0), (1, gz, gx == last), (2, gx, gz == last), (3, gz, gx == 0)] {
                        if on {
                            edge_d[e][k / q] = edge_d[e][k / q].max(g);
                        }
                    }
                    sq.min = c.iter().fold(sq.min, |m, v| m.min(v - g));
                    sq.max = c.iter().fold(sq.max, |m, v| m.max(v + g));
                    dmax = dmax.max(g);
                }
                let s = data.block(&grid, lod, bx, bz);
                assert_eq!((s.lo, s.hi, s.d), (lo, hi, dmax), "block {lod}/{bx}/{bz} of tile {level}/{tx}/{tz}");
                assert_eq!(s.squares, squares, "block {lod}/{bx}/{bz}'s squares");
                assert_eq!(s.edge_d, edge_d, "block {lod}/{bx}/{bz}'s edges");
                // The bound's premise: every full-resolution sample under a square is in
                // its heights, and the block's in the block's (within [lo - D, hi + D]).
                assert!(s.min >= lo - dmax && s.max <= hi + dmax, "block {lod}/{bx}/{bz}: {s:?}");
                for (x, z) in (0..=size).flat_map(|z| (0..=size).map(move |x| (x, z))) {
                    let h = hf.raw_at(ox + x, oz + z);
                    let (sx, sz) = (
                        ((x / (size / SUB as i64)) as usize).min(SUB - 1),
                        ((z / (size / SUB as i64)) as usize).min(SUB - 1),
                    );
                    let sq = &s.squares[sz * SUB + sx];
                    assert!(
                        h >= sq.min && h <= sq.max && h >= s.min && h <= s.max,
                        "sample ({x}, {z}) of block {lod}/{bx}/{bz}: {h} outside {sq:?}"
                    );
                }
                checked += 1;
            }
            // Every group's D as the morph reads it (`TileData::group_d`), the parent LOD's
            // from the tile serving it.
            if lod > 0 {
                let (groups, cells) = ((grid.tile_quads << level) >> lod, hf.cells(lod)[0]);
                for (gx, gz) in (0..groups).flat_map(|z| (0..groups).map(move |x| (x, z))) {
                    let (gx, gz) = (tx as usize * groups + gx, tz as usize * groups + gz);
                    assert_eq!(
                        data.group_d(&grid, lod, gx, gz),
                        d[lod as usize - 1][gz * cells + gx],
                        "D_{lod} ({gx}, {gz})"
                    );
                    groups_checked += 1;
                }
            }
        }
    }
    // Every group of LOD 1 and above once (LOD 0 has no D): 1024^2 / 4 + 1024^2 / 16 + ...
    assert_eq!(groups_checked, (1..=root).map(|l| (1024usize >> l).pow(2)).sum::<usize>());
    // 16 + 4 + 1 tiles of (256 / quads)^2 blocks, the top tile's coarser ones too
    // (16 + 4 + 1 for k = 33).
    let own = (256 / quads).pow(2);
    assert_eq!(checked, 21 * own + (1..=(256 / quads).trailing_zeros()).map(|j| own >> (2 * j)).sum::<usize>());
}

#[test]
fn settled_frames_keep_the_bound_cover_the_view_and_pass_the_audit() {
    let Fixture { hf, archive, grid, _dir } = fixture("stream-settled");
    let mm = MinMaxPyramid::build(&hf);
    // The paper's blocks, then the smallest and the largest a tile takes (`--block`).
    for k in [33, 9, 129] {
        let grid = grid.with_block(k).unwrap();
        let mut s = Streamer::new(archive.clone(), grid, 1 << 30);
        settled_frames_audit(&hf, &mm, &mut s);
    }
}

fn settled_frames_audit(hf: &Heightfield, mm: &MinMaxPyramid, s: &mut Streamer) {
    let k = s.grid.block_quads as u32 + 1;
    let layout = BlockLayout::of(hf, k).unwrap();
    let (mut lods, mut morphing) = (std::collections::BTreeSet::new(), 0);
    for (i, view) in poses().iter().enumerate() {
        let sel = settled(s, view, 12);
        let cam = camera(view);
        let blocks: Vec<DrawBlock> = sel.blocks.iter().map(|b| DrawBlock::new(b.lod, b.bx, b.bz)).collect();
        check_tiling(hf, mm, &layout, &blocks, &cam).unwrap_or_else(|e| panic!("k {k}, pose {i}: {e}"));
        assert_eq!(sel.stitched.len(), sel.blocks.len(), "k {k}, pose {i}: the selection is stitched as drawn");
        morphing += sel.morphing;
        for (b, block) in sel.blocks.iter().zip(&sel.stitched) {
            assert!(!b.over && (b.lod == 0 || b.error_px <= DELTA), "k {k}, pose {i}: {b:?}");
            let audited = audit_block(hf, &layout, block, &cam);
            assert!(audited <= DELTA * 1.001, "k {k}, pose {i}: block {b:?} audits at {audited} px");
            lods.insert(b.lod);
        }
        s.cache.check().unwrap();
    }
    // (Blocks of k = 129 cover the 1025^2 field with LODs 0 to 3.)
    assert!(lods.len() >= 3, "k {k}: the poses draw several LODs: {lods:?}");
    assert!(morphing > 50, "k {k}: {morphing} blocks morph over the poses");
    assert_eq!(s.stats.tiles_failed, 0);
}

/// A streamed frame's blocks, stitched from the held tiles alone, are the blocks the
/// in-memory code stitches from the whole heightfield (same neighbours, same resolved
/// corners), read the same samples, and are watertight: the GPU draws them with the same
/// placement as in memory.
#[test]
fn streamed_blocks_stitch_from_held_tiles_as_in_memory() {
    let Fixture { hf, archive, grid, _dir } = fixture("stream-stitch");
    let layout = BlockLayout::of(&hf, 33).unwrap();
    assert_eq!(draw::layout(&grid), layout, "the archive's block layout is the heightfield's");
    let mut s = Streamer::new(archive, grid, 1 << 30);
    let (mut stitched_edges, mut compared, mut morphing) = (0usize, 0usize, 0usize);
    for (i, view) in poses().iter().enumerate() {
        let sel = settled(&mut s, view, 12);
        let streamed = draw::stitched_blocks(&grid, &s.cache, &sel);
        let mut memory: Vec<DrawBlock> = sel.blocks.iter().map(|b| DrawBlock::new(b.lod, b.bx, b.bz)).collect();
        let map = stitch_selection(&hf, &layout, &mut memory);
        assert_eq!(streamed.len(), memory.len(), "pose {i}");
        morphing += sel.morphing;
        for (a, b) in streamed.iter().zip(&memory) {
            // The same blocks and neighbours; the streamed ones morph (what the
            // watertightness below checks with them).
            assert_eq!(a.block.unmorphed(), *b, "pose {i}");
            stitched_edges += b.coarser.iter().filter(|&&c| c > 0).count();
        }
        let resident = draw::Resident { grid: &grid, cache: &s.cache };
        let blocks: Vec<DrawBlock> = streamed.iter().map(|b| b.block).collect();
        compared +=
            common::assert_watertight(&resident, [hf.width, hf.height], &layout, &blocks, &map, &format!("pose {i}"));
        // Every vertex of every block, read from the held tiles, is the heightfield's.
        for b in &streamed {
            for v in 0..33 {
                for u in 0..33 {
                    let (x, z, h) = block_vertex(&resident, &layout, &b.block, u, v);
                    let (_, _, m) = block_vertex(&hf, &layout, &b.block, u, v);
                    assert_eq!(h.to_bits(), m.to_bits(), "pose {i}: {:?} vertex ({u}, {v}) at ({x}, {z})", b.block);
                }
            }
        }
    }
    assert!(stitched_edges > 100, "the poses stitch blocks to coarser neighbours: {stitched_edges}");
    assert!(compared > 10_000, "edge samples compared: {compared}");
    assert!(morphing > 100, "blocks morphing over the poses: {morphing}");
}

/// A sample no held tile has reads as NaN (so a block drawn from a missing tile cannot
/// pass as stitched), and held samples are the heightfield's.
#[test]
fn resident_samples_are_the_held_tiles_and_nothing_else() {
    let Fixture { hf, archive, grid, _dir } = fixture("stream-resident");
    let mut s = Streamer::new(archive, grid, 1 << 30);
    let view = poses()[0];
    let sel = settled(&mut s, &view, 12);
    let resident = draw::Resident { grid: &grid, cache: &s.cache };
    let level0: Vec<TileKey> = sel.used.iter().copied().filter(|k| k.level == 0).collect();
    assert!(!level0.is_empty());
    let span = grid.tile_span(0) as i64;
    for k in &level0 {
        for (x, z) in [(0, 0), (1, 7), (span, span), (span - 1, 3)] {
            let (x, z) = (k.tx as i64 * span + x, k.tz as i64 * span + z);
            if x < hf.width as i64 && z < hf.height as i64 {
                assert_eq!(resident.raw_at(x, z).to_bits(), hf.raw_at(x, z).to_bits(), "({x}, {z})");
            }
        }
    }
    // An odd sample outside every held level-0 tile.
    let missing = (0..grid.tiles_at(0)[0])
        .flat_map(|tx| (0..grid.tiles_at(0)[1]).map(move |tz| TileKey::new(0, tx, tz)))
        .find(|k| !s.cache.contains(*k))
        .expect("some level-0 tile is not held at one pose");
    let (x, z) = (missing.tx as i64 * span + 1, missing.tz as i64 * span + 3);
    assert!(resident.raw_at(x, z).is_nan(), "({x}, {z}) is in no held tile");
    assert!(resident.raw_at(-1, 0).is_nan());
}

/// The block bound without the deviation (`d` taken as 0) must fail the audit somewhere
/// on these poses: the audit above can fail.
#[test]
fn the_audit_catches_a_selection_that_ignores_the_deviation() {
    let hf = common::rough();
    let layout = BlockLayout::of(&hf, 33).unwrap();
    let worst = poses()
        .iter()
        .map(|view| {
            let cam = camera(view);
            // What a traversal that never splits would draw: the root's children.
            (0..4u32).map(|i| audit_block(&hf, &layout, &DrawBlock::new(4, i % 2, i / 2), &cam)).fold(0.0f32, f32::max)
        })
        .fold(0.0f32, f32::max);
    assert!(worst > 10.0 * DELTA, "coarse blocks audit at {worst} px");
}

/// Streamed frames geomorph inside the bound (`stream::morph`): over the poses and a
/// flight toward the horizon in short steps (blocks split and merge all along it, so
/// many are caught just past their split, where the ramp gives nothing and the factor
/// comes from the bound alone), every drawn block audits within delta on the rough field,
/// and a good share of the blocks is between its parent's surface and its own. The same
/// selections with the factors halved, or every block on its parent's surface, audit
/// over delta: the audit sees the morph. For the paper's blocks and the smallest a tile
/// takes (`--block 9`, whose squares are one quad: half a parent group).
#[test]
fn morphed_streamed_frames_audit_within_delta_and_an_underpaid_morph_does_not() {
    let Fixture { hf, archive, grid, _dir } = fixture("stream-morph");
    let mut views = poses();
    for i in 0..24 {
        let p = DVec3::new(200.0 + 37.0 * f64::from(i), 130.0, 300.0 + 83.0 * f64::from(i));
        views.push(View::look_at(p, p + DVec3::new(500.0, -40.0, 900.0), 45.0, 320, 240, 1.0));
    }
    for k in [33, 9] {
        morphed_frames_audit(&hf, &archive, grid.with_block(k).unwrap(), &views);
    }
    // Real terrain, whose deviations gather in a few squares of a block: low views over
    // Puget Sound 1k (160 m spacing), blocks of k = 9. Measured: a morph that took the
    // parent groups of only every other one-quad square audits at 1.05 px here, and
    // passes on the rough field.
    use vkterrain::input::load::{self, LoadOptions};
    let hf = load::load(&common::data("puget_sound/ps_height_1k.png"), &LoadOptions::default()).unwrap();
    let dir = TempDir::new("stream-morph-puget");
    let archive = common::archive_of(&hf, &dir);
    let views: Vec<View> = (0..12)
        .map(|i| {
            let a = f64::from(i) * std::f64::consts::TAU / 12.0;
            let p =
                DVec3::new(80000.0 + 50000.0 * a.cos(), 900.0 + 300.0 * f64::from(i % 3), 80000.0 + 50000.0 * a.sin());
            View::look_at(p, p + DVec3::new(-a.sin() * 60000.0, -900.0, a.cos() * 60000.0), 60.0, 480, 270, 8.0)
        })
        .collect();
    morphed_frames_audit(&hf, &archive, Grid::from_meta(&archive.meta).with_block(9).unwrap(), &views);
}

fn morphed_frames_audit(hf: &Heightfield, archive: &Arc<Archive>, grid: Grid, views: &[View]) {
    use vkterrain::lod::block::MORPH_ONE;
    use vkterrain::lod::morph::MorphRule;
    use vkterrain::stream::morph;
    use vkterrain::stream::traverse::StripCache;
    let k = grid.block_quads as u32 + 1;
    let layout = BlockLayout::of(hf, k).unwrap();
    let mut s = Streamer::new(archive.clone(), grid, 1 << 30);
    let strips = StripCache::with_entries(1 << 14);
    let (mut blocks, mut between, mut worst) = (0usize, 0usize, 0.0f32);
    let (mut underpaid, mut on_parent) = (0.0f32, 0.0f32);
    for (i, view) in views.iter().enumerate() {
        let sel = settled(&mut s, view, 12);
        let cam = camera(view);
        assert_eq!(sel.stitched.len(), sel.blocks.len());
        for (b, drawn) in sel.blocks.iter().zip(&sel.stitched) {
            let audited = audit_block(hf, &layout, drawn, &cam);
            assert!(audited <= DELTA * 1.001, "k {k}, view {i}: block {b:?} ({drawn:?}) audits at {audited} px");
            worst = worst.max(audited);
            between += usize::from(drawn.morph > 0 && drawn.morph < MORPH_ONE);
        }
        assert_eq!(
            sel.morphing,
            sel.stitched.iter().filter(|b| b.morph < MORPH_ONE || b.edge_morph.iter().any(|&e| e < MORPH_ONE)).count()
        );
        blocks += sel.blocks.len();
        for (rule, worst_broken) in [(MorphRule::Underpaid, &mut underpaid), (MorphRule::ParentSurface, &mut on_parent)]
        {
            let mut broken = sel.clone();
            broken.stitched.iter_mut().for_each(|b| *b = b.unmorphed());
            morph::assign(&grid, &s.cache, &strips, view, DELTA, &mut broken, rule);
            for drawn in &broken.stitched {
                *worst_broken = worst_broken.max(audit_block(hf, &layout, drawn, &cam));
            }
        }
    }
    println!("k {k}: {blocks} blocks, {between} between their parent's surface and their own, worst {worst:.3} px; broken: halved {underpaid:.2} px, on the parent {on_parent:.2} px");
    assert!(between * 5 > blocks, "k {k}: {between} of {blocks} blocks morph part way");
    assert!(underpaid > 1.2 * DELTA, "k {k}: factors halved audit at {underpaid} px");
    assert!(on_parent > 1.5 * DELTA, "k {k}: parents' surfaces audit at {on_parent} px");
}

/// `--traversal-threads` with streamed frames: the morph terms spread over a pool of
/// threads give every block the factors one thread gives it, in the same order, through
/// the streamer and through [`morph::assign`] alone on the same selection.
#[test]
fn streamed_morph_factors_are_the_same_on_any_number_of_threads() {
    use vkterrain::lod::block::TraversalPool;
    use vkterrain::lod::morph::MorphRule;
    use vkterrain::stream::morph;
    use vkterrain::stream::traverse::StripCache;
    let Fixture { hf: _, archive, grid, _dir } = fixture("stream-threads");
    let mut one = Streamer::new(archive.clone(), grid, 1 << 30);
    let mut three = Streamer::new(archive, grid, 1 << 30);
    three.set_threads(3).unwrap();
    assert_eq!((one.threads(), three.threads()), (1, 3));
    let pool = TraversalPool::new(3).unwrap();
    let strips = StripCache::with_entries(1 << 14);
    let mut morphing = 0;
    for (i, view) in poses().iter().enumerate() {
        let sel = settled(&mut one, view, 12);
        assert_eq!(settled(&mut three, view, 12).stitched, sel.stitched, "pose {i}: the streamers' frames");
        let mut again = sel.clone();
        again.stitched.iter_mut().for_each(|b| *b = b.unmorphed());
        let n = pool.install(|| morph::assign(&grid, &one.cache, &strips, view, DELTA, &mut again, MorphRule::Bounded));
        assert_eq!((n, &again.stitched), (sel.morphing, &sel.stitched), "pose {i}: assigned in the pool");
        morphing += sel.morphing;
    }
    assert!(morphing > 100, "{morphing} blocks morph: the factors compared are mostly 1");
}

/// `--lod full|distance` with streamed frames: under `Full` every settled block is at
/// LOD 0; under `Distance` no block is drawn coarser than the rings allow: each drawn
/// block of LOD > 0 is farther than twice its side, measured to its box from every
/// sample (no farther than the box the streamed rule measures, which holds its tile's
/// `D` too). Rings of 1.5 sides fail that check; the rule changes the selection (coarser
/// than full, other than the bound's) and nothing morphs outside the bound's rule.
#[test]
fn streamed_full_and_distance_lods_keep_their_rules() {
    use vkterrain::lod::block::block_aabb;
    use vkterrain::lod::camera::distance_to_aabb;
    use vkterrain::stream::traverse::StreamedLod;
    let Fixture { hf, archive, grid, _dir } = fixture("stream-lod-rules");
    let mm = MinMaxPyramid::build(&hf);
    let layout = BlockLayout::of(&hf, 33).unwrap();
    let mut s = Streamer::new(archive, grid, 1 << 30);
    let (mut coarse, mut closer_than_rings, mut fewer, mut other) = (0usize, 0usize, 0usize, 0usize);
    for (i, view) in poses().iter().enumerate() {
        s.lod = StreamedLod::Error;
        let bound = settled(&mut s, view, 12);
        s.lod = StreamedLod::Full;
        let full = settled(&mut s, view, 16);
        assert!(
            full.blocks.iter().all(|b| b.lod == 0),
            "pose {i}: full draws LOD {:?}",
            full.blocks.iter().map(|b| b.lod).max()
        );
        assert_eq!(full.morphing, 0, "pose {i}");
        let cam = camera(view);
        // The ring rule at `factor` against the samples' own boxes.
        let within_rings = |blocks: &[vkterrain::stream::traverse::Selected], factor: f32| {
            blocks.iter().filter(|b| b.lod > 0 && !b.t_junction).all(|b| {
                let (min, max) = block_aabb(&hf, &mm, &layout, b.lod, b.bx, b.bz);
                distance_to_aabb(cam.position, min, max) > factor * (max.x - min.x) * (1.0 - 1e-5)
            })
        };
        for factor in [2.0, 1.5] {
            s.lod = StreamedLod::Distance { factor };
            let rings = settled(&mut s, view, 12);
            assert_eq!(rings.morphing, 0, "pose {i}");
            assert!(
                within_rings(&rings.blocks, factor),
                "pose {i}: a block nearer than {factor} sides is drawn coarse"
            );
            if factor == 2.0 {
                fewer += usize::from(rings.blocks.len() < full.blocks.len());
                other += usize::from(rings.blocks != bound.blocks);
                coarse += rings.blocks.iter().filter(|b| b.lod > 0).count();
            } else {
                // The mutation: rings of 1.5 sides, checked as if they were of 2.
                closer_than_rings += usize::from(!within_rings(&rings.blocks, 2.0));
            }
        }
    }
    let poses = poses().len();
    println!("rings: {coarse} coarse blocks; fewer blocks than full at {fewer} of {poses} poses, other than the bound's at {other}; rings of 1.5 caught at {closer_than_rings}");
    assert!(coarse > 100, "{coarse} coarse blocks under the rings");
    assert!(
        fewer * 3 > poses * 2 && other * 3 > poses * 2,
        "rings fewer than full at {fewer}, other than the bound at {other} of {poses} poses"
    );
    assert!(closer_than_rings > 3, "rings of 1.5 sides passed the check of 2 at {closer_than_rings} poses");
}

/// What streamed morphing is for, as in memory (`tests/traversal.rs`,
/// `morphing_turns_jumps_into_small_steps`): along a low flight over Puget Sound in
/// short steps, the drawn surface of settled streamed frames moves a little everywhere
/// instead of jumping where blocks split or merge. The squared screen motion between
/// consecutive frames ([`common::surface_motion`]) with morphing against without.
#[test]
fn streamed_morphing_turns_jumps_into_small_steps() {
    use vkterrain::input::load::{self, LoadOptions};
    let hf = load::load(&common::data("puget_sound/ps_height_1k.png"), &LoadOptions::default()).unwrap();
    let dir = TempDir::new("stream-morph-motion");
    let archive = common::archive_of(&hf, &dir);
    let grid = Grid::from_meta(&archive.meta);
    let layout = BlockLayout::of(&hf, 33).unwrap();
    let (wx, wz) = hf.world_extent();
    let views: Vec<View> = (0..24)
        .map(|i| {
            let (x, z) = (wx * (0.3 + 0.004 * i as f32), wz * 0.6);
            let p = DVec3::new(f64::from(x), f64::from(hf.surface_height(x, z) + 600.0), f64::from(z));
            View::look_at(p, p + DVec3::new(1.0, -0.25, -0.3), 60.0, 640, 480, 8.0)
        })
        .collect();
    let mut motion = [0.0f64; 2];
    let mut partial = 0usize;
    for (on, total) in [false, true].into_iter().zip(motion.iter_mut()) {
        let mut s = Streamer::new(archive.clone(), grid, 1 << 30);
        if !on {
            s.morph = None;
        }
        let mut before: Option<Vec<f32>> = None;
        for view in &views {
            let sel = settled(&mut s, view, 16);
            let cam = camera(view);
            if on {
                partial +=
                    sel.stitched.iter().filter(|b| b.morph > 0 && b.morph < vkterrain::lod::block::MORPH_ONE).count();
            }
            let surface = common::drawn_surface(&hf, &layout, &sel.stitched);
            if let Some(b) = &before {
                *total += common::surface_motion(&hf, &cam, b, &surface);
            }
            before = Some(surface);
        }
    }
    let [off, on] = motion;
    println!("low flight, streamed: squared screen motion of the drawn surface, no morph {off:.0}, morph {on:.0} (ratio {:.3}); {partial} blocks part way", on / off);
    assert!(partial > views.len(), "too few morph states to test ({partial})");
    assert!(off > 0.0 && on < off / 2.0, "morphing {on}, without {off}");
}

#[test]
fn a_cache_too_small_for_the_path_counts_every_frame_over_the_bound_honestly() {
    let Fixture { hf, archive, grid, _dir } = fixture("stream-small");
    let layout = BlockLayout::of(&hf, 33).unwrap();
    let one = TileData::new(&grid, archive.read_tile(0, 0, 0).unwrap().unwrap()).unwrap().bytes;
    // The top tile, two of level 1 and three of level 0: less than most poses need.
    let mut s = Streamer::new(archive.clone(), grid, 6 * one + one / 2);
    let mut over_frames = 0;
    for (i, view) in poses().iter().cycle().take(60).enumerate() {
        let sel = s.frame(view, None, DELTA, 0.5);
        s.settle();
        s.cache.check().unwrap_or_else(|e| panic!("frame {i}: {e}"));
        let cam = camera(view);
        for (b, drawn) in sel.blocks.iter().zip(&sel.stitched) {
            // Used this frame, so not evicted by what the settle took in.
            assert!(s.cache.peek(b.tile).is_some(), "frame {i}: drawn from a tile not held");
            if b.over {
                // Its own error or its stitched strip's, or a T-junction.
                assert!(b.error_px > DELTA || b.t_junction, "frame {i}: {b:?}");
            } else {
                let audited = audit_block(&hf, &layout, drawn, &cam);
                assert!(audited <= DELTA * 1.001, "frame {i}: a block within the bound audits at {audited} px");
            }
        }
        let over = sel.blocks.iter().filter(|b| b.over).count();
        assert_eq!(over, sel.over_bound);
        if !sel.within_bound() {
            over_frames += 1;
            if sel.complete {
                let worst = sel.blocks.iter().filter(|b| b.over).map(|b| b.error_px / DELTA).fold(1.0f32, f32::max);
                assert_eq!(sel.worst_factor, worst);
            }
        }
    }
    assert_eq!(s.stats.frames_over_bound, over_frames);
    assert!(over_frames > 10, "the budget is too small for most poses: {over_frames} of 60 over");
    assert!(s.stats.tiles_evicted > 0 && s.stats.peak_cache_bytes <= 6 * one + one / 2, "{:?}", s.stats);
    assert!(s.stats.worst_factor > 1.0);
}

/// Random use of the cache against its rules: ancestor-closed, within budget, and no
/// tile the current frame used is evicted.
#[test]
fn the_host_cache_keeps_its_rules_under_random_use() {
    let Fixture { hf: _, archive, grid, _dir } = fixture("stream-cache");
    let tiles: Vec<Arc<TileData>> = archive
        .meta
        .tiles()
        .map(|(l, x, z)| Arc::new(TileData::new(&grid, archive.read_tile(l, x, z).unwrap().unwrap()).unwrap()))
        .collect();
    let (one, top_bytes) = (tiles[0].bytes, tiles.last().unwrap().bytes);
    let mut rng = 0x9e37_79b9_7f4a_7c15u64;
    let mut next = |n: usize| {
        rng ^= rng << 13;
        rng ^= rng >> 7;
        rng ^= rng << 17;
        (rng % n as u64) as usize
    };
    // The top tile and room for 2, 4, 8 and 40 level-0 tiles (a level-1 tile is almost
    // two).
    for budget_tiles in [2usize, 4, 8, 40] {
        let mut cache = HostCache::new(grid, top_bytes + budget_tiles * one + 100);
        let mut used_now = std::collections::HashSet::new();
        let mut kept_now = std::collections::HashSet::new();
        let (mut fulls, mut orphans) = (0, 0);
        for step in 0..3000 {
            match next(10) {
                0 => {
                    cache.begin_frame();
                    used_now.clear();
                    kept_now.clear();
                }
                1 | 2 => {
                    let k = tiles[next(tiles.len())].key;
                    if cache.contains(k) {
                        cache.mark_used([k]);
                        used_now.insert(k);
                    }
                }
                3 => {
                    let k = tiles[next(tiles.len())].key;
                    if cache.contains(k) {
                        cache.mark_kept([k]);
                        kept_now.insert(k);
                    }
                }
                _ => {
                    let t = tiles[next(tiles.len())].clone();
                    let key = t.key;
                    let needed = next(2) == 0;
                    let room = cache.room(needed, key.parent(grid.top));
                    let fits = t.bytes <= room;
                    let before: Vec<TileKey> = used_now.iter().copied().collect();
                    let kept_before: Vec<TileKey> = kept_now.iter().copied().filter(|k| cache.contains(*k)).collect();
                    let held_before = cache.contains(key);
                    let parent_held = key.parent(grid.top).is_none_or(|p| cache.contains(p));
                    let result = cache.insert(t, needed);
                    if !held_before && parent_held {
                        // What room() promises, insert() keeps (it may do better: a leaf
                        // evicted can leave its parent a leaf).
                        assert!(!fits || result.is_ok(), "step {step}: room {room}, needed {needed}: {result:?}");
                    }
                    if result.is_ok() && !needed {
                        for k in kept_before {
                            assert!(cache.contains(k), "step {step}: a prefetch evicted {k:?}, kept this frame");
                        }
                    }
                    match result {
                        Ok(()) => {}
                        Err(Refused::Full) => fulls += 1,
                        Err(Refused::NoParent) => {
                            orphans += 1;
                            assert!(!cache.contains(key.parent(grid.top).unwrap()));
                        }
                    }
                    for k in before {
                        assert!(cache.contains(k), "step {step}: {k:?} was used this frame and evicted");
                    }
                }
            }
            cache.check().unwrap_or_else(|e| panic!("budget {budget_tiles}, step {step}: {e}"));
        }
        assert!(orphans > 0, "the sequence tries orphans");
        if budget_tiles <= 8 {
            assert!(fulls > 0 && cache.stats.evicted > 0, "budget {budget_tiles}: {:?}", cache.stats);
        }
    }
}

/// A cache limited to as many tiles as an archive has (an atlas with a layer for each)
/// holds every one of them, whatever the budget's remainder over that count; and never
/// one more than the limit, however large the budget.
#[test]
fn a_cache_limited_to_every_tile_holds_every_tile() {
    let Fixture { hf: _, archive, grid, _dir } = fixture("stream-cache-limit");
    let mut tiles: Vec<Arc<TileData>> = archive
        .meta
        .tiles()
        .map(|(l, x, z)| Arc::new(TileData::new(&grid, archive.read_tile(l, x, z).unwrap().unwrap()).unwrap()))
        .collect();
    // Parents first (the cache is ancestor-closed).
    tiles.sort_by_key(|t| std::cmp::Reverse(t.key.level));
    let n = tiles.len();
    let largest = tiles.iter().map(|t| t.bytes).max().unwrap();
    // Budgets that leave a remainder over n (n - 1 of them: 1 to n - 1 bytes), and a huge one.
    for budget in [n * largest + 1, n * largest + n - 1, 1000 * n * largest] {
        let mut cache = HostCache::new(grid, budget);
        cache.limit_tiles(n);
        for t in &tiles {
            assert!(t.bytes.max(cache.floor()) <= cache.room(true, t.key.parent(grid.top)), "budget {budget}");
            cache.insert(t.clone(), true).unwrap_or_else(|e| panic!("budget {budget}, {:?}: {e:?}", t.key));
        }
        assert!(tiles.iter().all(|t| cache.contains(t.key)), "budget {budget}");
        cache.check().unwrap();
        // One tile fewer: the last one in is refused for want of a layer (nothing can be
        // evicted: every tile was used this frame).
        let mut fewer = HostCache::new(grid, budget);
        fewer.limit_tiles(n - 1);
        let keys: Vec<TileKey> = tiles.iter().map(|t| t.key).collect();
        for (i, t) in tiles.iter().enumerate() {
            let r = fewer.insert(t.clone(), true);
            let held: Vec<TileKey> = keys[..=i].iter().copied().filter(|&k| fewer.contains(k)).collect();
            fewer.mark_used(held);
            assert_eq!(r.is_ok(), i < n - 1, "budget {budget}, tile {i} of {n}: {r:?}");
        }
    }
}

/// A source whose chosen tiles fail (a damaged tile, a file gone): the frames degrade to
/// coarser blocks, counted, the failure is reported once with the tile, and the tile is
/// asked for again after RETRY_FRAMES.
struct Flaky {
    archive: Arc<Archive>,
    bad: TileKey,
    reads: std::sync::Mutex<Vec<TileKey>>,
}

impl TileSource for Flaky {
    fn read(&self, key: TileKey) -> Result<Option<(vkterrain::input::archive::tile::Tile, u64)>, String> {
        self.reads.lock().unwrap().push(key);
        if key == self.bad {
            return Err(format!("tile {}/{}/{}: read failed: the file is gone", key.level, key.tx, key.tz));
        }
        self.archive.read(key)
    }
}

#[test]
fn a_failing_tile_degrades_the_frame_and_is_retried() {
    let Fixture { hf: _, archive, grid, _dir } = fixture("stream-flaky");
    let view = poses()[0];
    // The level-1 tile under the camera.
    let [sx, sz] = grid.sample_of(view.position.x, view.position.z);
    let bad = TileKey::new(1, (sx / 512.0) as u32, (sz / 512.0) as u32);
    let flaky = Arc::new(Flaky { archive, bad, reads: Default::default() });
    let mut s = Streamer::new(flaky.clone(), grid, 1 << 30);
    for _ in 0..8 {
        s.frame(&view, None, DELTA, 0.0);
        s.settle();
    }
    let sel = s.frame(&view, None, DELTA, 0.0);
    assert!(!sel.within_bound() && sel.over_bound > 0, "the missing tile leaves blocks over the bound");
    assert!(sel.blocks.iter().all(|b| b.tile != bad));
    assert!(s.first_failure.as_deref().unwrap().contains("tile 1/"), "{:?}", s.first_failure);
    let reads_of = |k| flaky.reads.lock().unwrap().iter().filter(|r| **r == k).count();
    assert_eq!(reads_of(bad), 1, "not read again every frame");
    for _ in 0..RETRY_FRAMES + 2 {
        s.frame(&view, None, DELTA, 0.0);
        s.settle();
    }
    assert_eq!(reads_of(bad), 2, "asked for again after {RETRY_FRAMES} frames");
    assert_eq!(s.stats.tiles_failed, 2);
}

/// The same terrain 1e7 and 1e8 world units from the origin, the camera moved with it:
/// the same blocks at the same errors, bit for bit (positions are f64 until they are
/// relative to the camera's sample). In f32, 1e8 is a multiple of 8: every position on
/// this 3 x 5 grid would round.
#[test]
fn far_from_the_origin_the_frames_are_the_same() {
    let Fixture { hf: _, archive, grid, _dir } = fixture("stream-far");
    let mut near = Streamer::new(archive.clone(), grid, 1 << 30);
    let reference: Vec<Selection> = poses().iter().map(|v| settled(&mut near, v, 12)).collect();
    for offset in [1e7, 1e8, -1e8] {
        let far_grid = grid.at([offset, 3.0 * offset]);
        let mut far = Streamer::new(archive.clone(), far_grid, 1 << 30);
        for (i, (view, want)) in poses().iter().zip(&reference).enumerate() {
            let moved = View { position: view.position + DVec3::new(offset, 0.0, 3.0 * offset), ..*view };
            let got = settled(&mut far, &moved, 12);
            assert_eq!(got.blocks, want.blocks, "offset {offset}, pose {i}");
        }
        // What f32 world positions would have lost: some poses' x do not survive the
        // round trip (at 1e7 the integer ones do; at 1e8 none).
        let lost =
            poses().iter().filter(|v| f64::from((v.position.x + offset) as f32) != v.position.x + offset).count();
        assert!(lost > 0, "offset {offset}: f32 would keep every position exactly");
    }
}

/// `vkterrain stream` end to end on a small prepared archive: a flight over more tiles
/// than the cache holds evicts, stays within its budget and reports frames over the
/// bound consistently; over a truncated copy it degrades (exit 0, the damaged tile
/// named), it does not stop.
#[test]
fn the_stream_command_flies_within_its_budget_and_degrades_on_a_damaged_archive() {
    let dir = TempDir::new("stream-cli");
    let archive = dir.path().join("s.pmtiles");
    let a = archive.to_str().unwrap();
    let o = cli(&["prepare", "--synthetic", "2049", "--out", a]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    // RUST_LOG unset, as a user runs it (the tests' runner asks for errors only).
    let fly = |path: &str| {
        let args = ["stream", path, "--cache-mb", "8", "--frames", "360", "--fps", "120", "--speed", "8000", "--cold"];
        let o = common::run_bounded_logging(&args.map(String::from), 600, None);
        // 0 clean, 3 finished degraded (tiles failed): the JSON says which.
        let r = serde_json::from_slice::<serde_json::Value>(&o.stdout).unwrap();
        let degraded = r["degraded"].as_bool().unwrap_or_else(|| panic!("no degraded fact: {r}"));
        assert_eq!(o.status.code(), Some(if degraded { 3 } else { 0 }), "{}", String::from_utf8_lossy(&o.stderr));
        // Warnings read as the program's other messages, one line each.
        let err = String::from_utf8_lossy(&o.stderr);
        for line in err.lines().filter(|l| l.contains("streaming:")) {
            assert!(line.starts_with("vkterrain: warning: streaming: "), "{line}");
        }
        (r, err.contains("vkterrain: warning: streaming: "))
    };
    // A frame's step longer than the flight's whole line is refused (exit 2), not flown.
    let o = cli(&["stream", a, "--frames", "10", "--speed", "1e30"]);
    let err = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(2), "{err}");
    assert!(err.contains("--speed 1e30") && err.contains("longer than the flight's line across"), "{err}");
    // A frame larger than the device's images, or a negative number, is a bad option too.
    for (args, needle) in [
        (&["--gpu-mb", "16", "--size", "16385x8"][..], "--size 16385x8: larger than the device's maxImageDimension2D"),
        (&["--fps", "-1"][..], "--fps"),
    ] {
        let o = cli(&[&["stream", a, "--frames", "2"][..], args].concat());
        let err = String::from_utf8_lossy(&o.stderr);
        assert_eq!(o.status.code(), Some(2), "{err}");
        assert!(err.contains(needle) && !err.contains("unexpected argument"), "{err}");
    }
    // Top tiles that cannot be read (the tile data's offset moved past the file's end):
    // nothing could be drawn, so the flight is refused naming why (exit 2), as `render`
    // refuses it, not flown as frames of nothing.
    let mut moved = std::fs::read(&archive).unwrap();
    moved[56..64].copy_from_slice(&(1u64 << 40).to_le_bytes());
    let moved_path = dir.path().join("moved.pmtiles");
    std::fs::write(&moved_path, &moved).unwrap();
    let o = cli(&["stream", moved_path.to_str().unwrap(), "--frames", "10"]);
    let err = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(2), "{err}");
    assert!(err.contains("top tiles could not be read") && err.contains("moved.pmtiles"), "{err}");
    let (r, _) = fly(a);
    let stats = &r["stats"];
    assert_eq!(r["frames"], 360);
    assert_eq!(r["frames_over_bound"], stats["frames_over_bound"]);
    assert!(stats["tiles_evicted"].as_u64().unwrap() > 0, "{r}");
    assert!(stats["peak_cache_bytes"].as_u64().unwrap() <= 8 << 20, "{r}");
    assert!(r["distinct_over_cache"].as_f64().unwrap() > 1.0, "the flight sees more than the cache holds: {r}");
    assert!(r["first_failure"].is_null(), "{r}");
    assert_eq!(r["degraded"], false);
    let bytes = std::fs::read(&archive).unwrap();
    let cut = dir.path().join("cut.pmtiles");
    std::fs::write(&cut, &bytes[..bytes.len() / 2]).unwrap();
    let (r, warned) = fly(cut.to_str().unwrap());
    assert!(warned, "the damaged tiles are warned about");
    let failure = r["first_failure"].as_str().unwrap_or_else(|| panic!("no failure reported: {r}"));
    assert!(failure.contains("cut.pmtiles") && failure.contains("tile ") && failure.contains("truncated"), "{failure}");
    assert!(r["stats"]["tiles_failed"].as_u64().unwrap() > 0);
    assert_eq!(r["degraded"], true, "tiles failed: the flight finished degraded (exit 3)");
}

/// A field made to break stitching (SPEC section 5): the LOD-2 mesh of random vertices
/// (so `D_2 = 0` and LOD-2 blocks have no error of their own) beside flat ground, whose
/// coarse blocks meet them. The fan triangles of a stitched strip cut across the LOD-2
/// quads, departing from the true surface by up to the vertices' spread while every block
/// error is 0. Settled streamed frames, as drawn (stitched), audit within delta; the same
/// frames selected without the stitching rule audit far over it (the check can fail).
#[test]
fn stitched_strips_stay_within_the_bound_on_a_field_made_to_break_them() {
    for amplitude in [5.0f32, 0.5] {
        let node = move |i: usize, j: usize| {
            if i * 4 <= 256 || j * 4 <= 128 {
                return 0.0;
            }
            let mut n = (i as u64).wrapping_mul(0x9E3779B97F4A7C15) ^ (j as u64).wrapping_mul(0xC2B2AE3D27D4EB4F);
            n ^= n >> 29;
            n = n.wrapping_mul(0xBF58476D1CE4E5B9);
            n ^= n >> 32;
            (n % 1000) as f32 / 1000.0 * amplitude
        };
        let hf = common::field(513, 513, 1.0, move |x, z| {
            let (i, j) = (x / 4, z / 4);
            let (fx, fz) = ((x % 4) as f32 / 4.0, (z % 4) as f32 / 4.0);
            let (a, c, g, ii) = (node(i, j), node(i + 1, j), node(i, j + 1), node(i + 1, j + 1));
            // The a-i split: above the diagonal the triangle a-c-i, below it a-i-g.
            if fx >= fz {
                a + (c - a) * fx + (ii - c) * fz
            } else {
                a + (ii - g) * fx + (g - a) * fz
            }
        });
        let dir = TempDir::new("stream-strips");
        let archive = common::archive_of(&hf, &dir);
        let grid = Grid::from_meta(&archive.meta);
        let layout = BlockLayout::of(&hf, 33).unwrap();
        let mut s = Streamer::new(archive, grid, 1 << 30);
        let (mut drawn_worst, mut unruled_worst, mut splits) = (0.0f32, 0.0f32, 0);
        for i in 0..40 {
            let a = i as f64 * 0.37;
            let h = [2.0, 10.0, 40.0, 150.0][i % 4];
            let p = DVec3::new(256.0 + 20.0 * a.cos(), h + f64::from(amplitude), 300.0 + 150.0 * a.sin());
            let t = DVec3::new(256.0 + 30.0 * (a * 1.7).sin(), 0.0, 300.0 + 100.0 * (a * 2.3).cos());
            let view = View::look_at(p, t, [30.0, 60.0, 90.0][i % 3], 640, 480, 0.01);
            let sel = settled(&mut s, &view, 12);
            let cam = camera(&view);
            splits += sel.stitch_splits;
            for (b, drawn) in sel.blocks.iter().zip(&sel.stitched) {
                let audited = audit_block(&hf, &layout, drawn, &cam);
                assert!(audited <= DELTA * 1.001, "amplitude {amplitude} pose {i}: {b:?} audits at {audited} px");
                drawn_worst = drawn_worst.max(audited);
            }
            let unruled = select(&grid, &s.cache, &view, DELTA, 1.0, None);
            for b in draw::stitched_blocks(&grid, &s.cache, &unruled) {
                unruled_worst = unruled_worst.max(audit_block(&hf, &layout, &b.block, &cam));
            }
        }
        println!("amplitude {amplitude}: stitched frames audit at {drawn_worst} px, {unruled_worst} px without the rule; {splits} stitch splits");
        assert!(
            unruled_worst > 5.0 * DELTA,
            "amplitude {amplitude}: the field does not break stitching: {unruled_worst}"
        );
        assert!(splits > 0);
    }
}

/// Real terrain, the flight case: settled streamed frames over Puget Sound 1k from low
/// cameras looking toward the horizon (and a few looking down) audit within delta, every
/// block as drawn (stitched), exactly measured against the full-resolution samples. The
/// bound's squares and edge rows (SPEC 8, `stream::traverse`) hold on data nobody made
/// to fit them, and stay tight (the worst block near delta).
#[test]
fn streamed_frames_over_real_terrain_audit_within_delta() {
    use vkterrain::input::load::{self, LoadOptions};
    let hf = load::load(&common::data("puget_sound/ps_height_1k.png"), &LoadOptions::default()).unwrap();
    let dir = TempDir::new("stream-real");
    let archive = common::archive_of(&hf, &dir);
    let grid = Grid::from_meta(&archive.meta);
    let layout = BlockLayout::of(&hf, 33).unwrap();
    let mut s = Streamer::new(archive, grid, 1 << 30);
    let (wx, wz) = hf.world_extent();
    let (mut worst, mut blocks) = (0.0f32, 0usize);
    for i in 0..16 {
        let a = i as f64 * std::f64::consts::TAU / 16.0;
        let (x, z) = (f64::from(wx) * (0.5 + 0.3 * a.cos()), f64::from(wz) * (0.5 + 0.3 * a.sin()));
        let ground = f64::from(hf.surface_height(x as f32, z as f32));
        // 150 to 1,350 m over the ground, heading across the terrain, 3 degrees down;
        // every fourth looks steeply down.
        let p = DVec3::new(x, ground + 150.0 + 400.0 * (i % 4) as f64, z);
        let down = if i % 4 == 3 { 0.8 } else { 0.05 };
        let t = p + DVec3::new(-a.sin(), -down, a.cos()) * 1000.0;
        let view = View::look_at(p, t, 45.0, 320, 240, 1.0);
        let sel = settled(&mut s, &view, 16);
        let cam = camera(&view);
        assert_eq!(sel.stitched.len(), sel.blocks.len());
        for (b, drawn) in sel.blocks.iter().zip(&sel.stitched) {
            let audited = audit_block(&hf, &layout, drawn, &cam);
            assert!(audited <= DELTA * 1.001, "pose {i}: block {b:?} audits at {audited} px");
            worst = worst.max(audited);
        }
        blocks += sel.blocks.len();
    }
    println!("{blocks} blocks over 16 poses, worst {worst:.3} px");
    assert!(blocks > 500, "{blocks} blocks");
    assert!(worst > 0.5 * DELTA, "the bound is that loose? worst {worst} px");
}

/// The boxes streamed frames cull parts by (`draw::part_boxes`, from each tile's square
/// summaries) hold every vertex of their part's triangles, read from the held tiles, at
/// the poses' settled frames: as drawn (stitched), and with coarser neighbours 1 to m
/// LODs coarser put on random edges and random resolved corners (where stitched vertices
/// collapse along a neighbour's longer segment). Mutation: boxes made as if no neighbour
/// were coarser let those vertices escape.
#[test]
fn streamed_part_boxes_hold_their_triangles() {
    let Fixture { archive, grid, _dir, .. } = fixture("stream-part-boxes");
    let layout = draw::layout(&grid);
    let (_, idx) = vkterrain::lod::block::block_mesh_data(layout.k());
    let per_part = idx.len() / layout.parts_per_side().pow(2) as usize;
    let mut s = Streamer::new(archive, grid, 1 << 30);
    let mut state = 0x9e37_79b9_u64;
    let mut rng = |k: u32| {
        state = state.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
        ((state >> 33) % u64::from(k)) as u32
    };
    let (mut listed, mut variants, mut escaped_when_unstitched) = (0usize, 0usize, 0usize);
    for (i, view) in poses().iter().enumerate() {
        let sel = settled(&mut s, view, 12);
        let resident = draw::Resident { grid: &grid, cache: &s.cache };
        // Vertices of `drawn`'s listed parts outside the boxes made for `boxed`.
        let escapes = |drawn: &draw::StreamedBlock, boxed: &draw::StreamedBlock| {
            let boxes = draw::part_boxes(&grid, &s.cache, boxed).expect("a drawn block's tile is held");
            let mut out = 0;
            for pb in &boxes {
                let part = pb.bit.trailing_zeros() as usize;
                for &j in &idx[part * per_part..(part + 1) * per_part] {
                    let (sx, sz, raw) = block_vertex(&resident, &layout, &drawn.block, j % layout.k(), j / layout.k());
                    let inside = (pb.x0..=pb.x0 + pb.size).contains(&sx)
                        && (pb.z0..=pb.z0 + pb.size).contains(&sz)
                        && (pb.raw[0]..=pb.raw[1]).contains(&raw);
                    out += usize::from(!inside);
                }
            }
            (boxes.len(), out)
        };
        for sb in draw::stitched_blocks(&grid, &s.cache, &sel) {
            let mut variant = sb;
            let lod = sb.block.lod;
            for e in 0..4 {
                if rng(2) == 0 && variant.block.coarser[e] == 0 {
                    variant.block.coarser[e] = 1 << (lod + 1 + rng(layout.m));
                }
            }
            for c in 0..4 {
                if rng(3) == 0 {
                    variant.block.corner_raw[c] = (rng(2000) as f32 * 0.1 - 50.0).to_bits();
                }
            }
            for b in [sb, variant] {
                let (n, out) = escapes(&b, &b);
                assert_eq!(out, 0, "pose {i}: {:?}: vertices outside their part's box", b.block);
                listed += n;
                let unstitched = draw::StreamedBlock { block: DrawBlock { coarser: [0; 4], ..b.block }, ..b };
                escaped_when_unstitched += escapes(&b, &unstitched).1;
            }
            variants += 1;
        }
    }
    assert!(variants > 500 && listed > 10_000, "{variants} blocks, {listed} parts listed");
    assert!(escaped_when_unstitched > 0, "mutation: boxes blind to coarser neighbours went unnoticed");
}

/// How the traversal takes the errors activity's block errors ([`TileErrors`]): the
/// smaller of them and the tile's own bound. Errors above the tile's bound change
/// nothing; zero errors at the camera stop every split; infinite ones (a `D` past the
/// half floats' range), errors from a camera that may have come inside a block's
/// distance and errors for another height scale bound nothing, and are counted as the
/// tile's.
#[test]
fn the_traversal_takes_the_smaller_of_the_gpu_errors_and_the_tiles_bound() {
    use vkterrain::stream::errors::TileErrors;
    use vkterrain::stream::traverse::{select_by, StreamedLod};
    let Fixture { archive, grid, _dir, .. } = fixture("stream-gpu-errors");
    let mut s = Streamer::new(archive, grid, 1 << 30);
    let view = poses()[0];
    let cpu = settled(&mut s, &view, 12);
    let per_tile = (grid.tile_quads / grid.block_quads).pow(2);
    const STRICT: (StreamedLod, f32, vkterrain::lod::gie::ErrorMode) =
        (StreamedLod::Error, DELTA, vkterrain::lod::gie::ErrorMode::Strict);
    let errors_of = |value: f32, position: DVec3| TileErrors {
        generation: 7,
        position,
        kappa: camera(&view).kappa(),
        height_scale: grid.height_scale,
        gpu_ms: None,
        tiles: s.cache.tiles().iter().filter(|t| t.key.level > 0).map(|t| (t.key, vec![value; per_tile])).collect(),
        ..TileErrors::default()
    };
    let with = |e: &TileErrors| select_by(&grid, &s.cache, &view, STRICT, 1.0, None, Some(e));
    let lods = |sel: &Selection| sel.blocks.iter().map(|b| (b.lod, b.bx, b.bz)).collect::<Vec<_>>();
    let plain = select_by(&grid, &s.cache, &view, STRICT, 1.0, None, None);
    assert_eq!((plain.errors_from_gpu, plain.errors_generation), (0, 0));
    // Larger than every tile bound: the same blocks, each taken from the generation.
    let large = with(&errors_of(1e30, view.position));
    assert_eq!(lods(&large), lods(&plain));
    assert!(
        large.errors_from_gpu > 10 && large.errors_from_tiles == 0,
        "{} {}",
        large.errors_from_gpu,
        large.errors_from_tiles
    );
    assert_eq!(large.errors_generation, 7);
    // Zero at this camera: no block of a shaded tile splits.
    let zero = with(&errors_of(0.0, view.position));
    assert!(
        zero.blocks.len() < plain.blocks.len() && zero.errors_from_gpu > 0,
        "{} {}",
        zero.blocks.len(),
        plain.blocks.len()
    );
    // Infinite: no bound, the tile's.
    let inf = with(&errors_of(f32::INFINITY, view.position));
    assert_eq!(lods(&inf), lods(&plain));
    assert_eq!(inf.errors_from_gpu, 0);
    assert_eq!(inf.errors_from_tiles, large.errors_from_gpu);
    // Zero, but for a camera 1 km away: the move may bring it inside the distance of the
    // blocks near it, whose bound is then the tile's (they split again).
    let far = with(&errors_of(0.0, view.position + DVec3::new(1000.0, 0.0, 0.0)));
    assert!(
        far.errors_from_tiles > 0 && far.blocks.len() > zero.blocks.len(),
        "{} {}",
        far.errors_from_tiles,
        far.blocks.len()
    );
    // Zero, but for other heights (the viewer's exaggeration since): bounds nothing.
    let rescaled = with(&TileErrors { height_scale: grid.height_scale * 2.0, ..errors_of(0.0, view.position) });
    assert_eq!(lods(&rescaled), lods(&plain));
    assert_eq!(rescaled.errors_from_gpu, 0);
    // Zero for a camera a metre away: taken, corrected, still zero.
    let near = with(&errors_of(0.0, view.position + DVec3::new(1.0, 0.0, 0.0)));
    assert!(near.errors_from_gpu > 0 && near.errors_stale_worst > 1.0);
    drop(cpu);
}
