//! A streamed frame's blocks as the vertex shader draws them (SPEC sections 5 and 8):
//! each selected block with its coarser neighbours' strides and resolved corners, read
//! from the tiles the frame holds, and the atlas layer its heights come from. The
//! stitching is the in-memory traversal's own ([`stitch_blocks`]); only where the
//! samples come from ([`Resident`]) and how neighbours are found ([`SparseLods`]) differ.

pub use super::cache::{layout, Resident};
use super::cache::{HostCache, SUB};
use super::traverse::{square_of_samples_box, Selection};
use super::{Grid, TileKey};
use crate::lod::block::{
    part_boxes_by, DrawBlock, OcclusionReport, PartBox, Skipped, CORNER_UNRESOLVED, PART_FRUSTUM_MARGIN_PX,
};
use crate::lod::camera::Camera;
use crate::lod::occlusion::{part_of, Rect, Rule, SweptBlock, SweptFrame};
use crate::lod::stitch::{coarser_sides, strip_departure};
use crate::lod::traversal::{stitch_blocks, LodAt, SparseLods};

/// A block to draw and where its heights are: the tile it is drawn from.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct StreamedBlock {
    pub block: DrawBlock,
    pub tile: TileKey,
    /// Drawn by rays (`--raycast`, `app::stream::choose_raycast`): the raw height range of the
    /// vertices the rays meet, its resolved corners included; `None`: rasterized.
    pub raycast: Option<[f32; 2]>,
}

/// The blocks of `sel` stitched to each other, with the tiles they are drawn from: as the
/// selection stitched (and morphed, [`super::morph`]) them, or (a selection made without
/// the stitching rule) stitched here, unmorphed.
pub fn stitched_blocks(grid: &Grid, cache: &HostCache, sel: &Selection) -> Vec<StreamedBlock> {
    let blocks = if sel.stitched.len() == sel.blocks.len() {
        sel.stitched.clone()
    } else {
        let mut blocks: Vec<DrawBlock> = sel.blocks.iter().map(|b| DrawBlock::new(b.lod, b.bx, b.bz)).collect();
        let layout = layout(grid);
        let lods = SparseLods::new(&layout, &blocks);
        stitch_blocks(&Resident { grid, cache }, &layout, &mut blocks, &lods);
        blocks
    };
    // Blocks occlusion culling hid whole in a frame drawn again (a bench's ceiling) stay out.
    let all = layout(grid).all_parts();
    blocks
        .into_iter()
        .zip(&sel.blocks)
        .filter(|(block, _)| block.hidden_parts != all)
        .map(|(block, s)| StreamedBlock { block, tile: s.tile, raycast: None })
        .collect()
}

/// The parts of a streamed block that can be left out alone, with their boxes
/// ([`part_boxes_by`]): each part's heights are the range of the squares of its tile's
/// summary it covers, which holds every sample under them and every point of the
/// block's surface and its parent's (a morphed vertex lies between its sample and the
/// mean of two samples of its square). `None` when its tile is not held.
pub fn part_boxes(grid: &Grid, cache: &HostCache, sb: &StreamedBlock) -> Option<Vec<PartBox>> {
    let b = &sb.block;
    let summary = cache.peek(sb.tile)?.block(grid, b.lod, b.bx, b.bz);
    let layout = layout(grid);
    let per_part = SUB as u32 / layout.parts_per_side();
    let raw = |px: u32, pz: u32| {
        let mut r = [f32::INFINITY, f32::NEG_INFINITY];
        for sz in pz * per_part..(pz + 1) * per_part {
            for sx in px * per_part..(px + 1) * per_part {
                let sq = &summary.squares[sz as usize * SUB + sx as usize];
                r = [r[0].min(sq.min), r[1].max(sq.max)];
            }
        }
        r
    };
    Some(part_boxes_by(&layout, b, raw).collect())
}

/// Leaves out of `blocks` the parts whose boxes lie wholly outside `cam`'s frustum (the
/// camera relative to sample `anchor`) widened by [`PART_FRUSTUM_MARGIN_PX`], as the
/// in-memory frame does ([`crate::lod::block::hide_parts_outside`]); returns how many
/// parts that hid. The blocks stay: stitching and the bound see nothing new.
pub fn hide_parts_outside(
    grid: &Grid,
    cache: &HostCache,
    anchor: [i64; 2],
    cam: &Camera,
    blocks: &mut [StreamedBlock],
) -> usize {
    hide_parts_outside_by(grid, cache, anchor, cam, PART_FRUSTUM_MARGIN_PX, blocks)
}

/// [`hide_parts_outside`] with the frustum widened by `margin_px` (tests narrow it to
/// show that their check catches visible parts left out).
pub fn hide_parts_outside_by(
    grid: &Grid,
    cache: &HostCache,
    anchor: [i64; 2],
    cam: &Camera,
    margin_px: f32,
    blocks: &mut [StreamedBlock],
) -> usize {
    let frustum = cam.frustum_widened(margin_px);
    let mut hidden = 0;
    for sb in blocks.iter_mut() {
        let Some(boxes) = part_boxes(grid, cache, sb) else { continue };
        let outside = boxes
            .iter()
            .filter(|pb| {
                let (min, max) = square_of_samples_box(grid, anchor, [pb.x0, pb.z0], pb.size, pb.raw[0], pb.raw[1]);
                !frustum.intersects_aabb(min, max)
            })
            .fold(0u16, |h, pb| h | pb.bit)
            & !sb.block.hidden_parts;
        hidden += outside.count_ones() as usize;
        sb.block.hidden_parts |= outside;
    }
    hidden
}

/// A frustum-culled block of a selection ([`Selection::frustum_culled`]): LOD, place and
/// lowest sample (raw).
pub type CulledBlock = (u32, u32, u32, f32);

/// Per block of `blocks` (the drawn blocks of a selection whose frustum-culled blocks are
/// `culled`, [`Selection::frustum_culled`]), its parts that no pixel can see for `cam`
/// (relative to sample `anchor`), by occlusion culling's sweep
/// ([`crate::lod::occlusion::sweep`], its argument in that module), from the tiles'
/// summaries: a block's drawn range is its squares' heights widened by its stitched
/// strips and resolved corners, and each square of its footprint occludes under its
/// lowest height (under the block's lowest where it lies along an edge stitched to a
/// coarser block, or holds a resolved corner). Skipped, with the reason, where the
/// argument needs what the tiles cannot show: a drawn block whose tile is not held (or
/// not `drawable`: its surface would be missing), or a drawn block beside a culled one `m`
/// or more LODs coarser.
pub fn hidden_parts(
    grid: &Grid,
    cache: &HostCache,
    (anchor, cam): ([i64; 2], &Camera),
    (blocks, culled): (&[StreamedBlock], &[CulledBlock]),
    drawable: &dyn Fn(TileKey) -> bool,
    rule: Rule,
) -> Result<Vec<u16>, Skipped> {
    // A hole shows what is behind it: no surface is known to hide anything.
    if grid.holes {
        return Err(Skipped::Holes);
    }
    let layout = layout(grid);
    let drawn: Vec<DrawBlock> = blocks.iter().map(|b| b.block).collect();
    let lods = SparseLods::new(&layout, &drawn);
    let coarse_beside = |&(lod, bx, bz, _): &CulledBlock| {
        DrawBlock::new(lod, bx, bz).cells_across().into_iter().any(|(x, z)| {
            let l = lods.lod_at(x, z, lod);
            l >= 0 && l as u32 >= lod + layout.m
        })
    };
    if culled.iter().any(coarse_beside) {
        return Err(Skipped::CoarseBesideCulled);
    }
    let (sx, sz, hs) = (grid.spacing[0], grid.spacing[1], grid.height_scale);
    // Samples from `anchor`, in world units.
    let rect = |x0: i64, z0: i64, size: i64| {
        let (x, z) = ((x0 - anchor[0]) as f64 * sx, (z0 - anchor[1]) as f64 * sz);
        Rect { x0: x, z0: z, x1: x + size as f64 * sx, z1: z + size as f64 * sz }
    };
    let extent = {
        let r = rect(0, 0, 0);
        Rect { x1: r.x0 + (grid.width - 1) as f64 * sx, z1: r.z0 + (grid.height - 1) as f64 * sz, ..r }
    };
    let l = &layout;
    let mut swept = Vec::with_capacity(blocks.len());
    let mut tops = Vec::with_capacity(blocks.len());
    for sb in blocks {
        let b = &sb.block;
        let tile = cache.peek(sb.tile).filter(|_| drawable(sb.tile)).ok_or(Skipped::TileMissing)?;
        let s = tile.block(grid, b.lod, b.bx, b.bz);
        let (mut lo, mut hi) = (s.min, s.max);
        if coarser_sides(b) != 0 {
            let d = strip_departure(&Resident { grid, cache }, l, b);
            (lo, hi) = (lo.min(d.lo), hi.max(d.hi));
        }
        let corners: Vec<(usize, f32)> = (0..4)
            .filter(|&c| b.corner_raw[c] != CORNER_UNRESOLVED)
            .map(|c| (c, f32::from_bits(b.corner_raw[c])))
            .collect();
        for &(_, h) in &corners {
            (lo, hi) = (lo.min(h), hi.max(h));
        }
        let size = (grid.block_quads << b.lod) as i64;
        let (ox, oz) = (i64::from(b.bx) * size, i64::from(b.bz) * size);
        let square = size / SUB as i64;
        let last = SUB - 1;
        let corner_square = [(0, 0), (last, 0), (last, last), (0, last)];
        // Per square: its footprint and the heights the drawn surface over it keeps to
        // (the block's whole range along a stitched edge or at a resolved corner).
        let squares: Vec<(Rect, f64, f64)> = (0..SUB * SUB)
            .map(|i| {
                let (qx, qz) = (i % SUB, i / SUB);
                let on_edge = [qz == 0, qx == last, qz == last, qx == 0];
                let (mut cell_lo, mut cell_hi) = (s.squares[i].min, s.squares[i].max);
                if (0..4).any(|e| on_edge[e] && b.coarser[e] > 0)
                    || corners.iter().any(|&(c, _)| corner_square[c] == (qx, qz))
                {
                    (cell_lo, cell_hi) = (cell_lo.min(lo), cell_hi.max(hi));
                }
                let r = rect(ox + qx as i64 * square, oz + qz as i64 * square, square);
                (r, f64::from(cell_lo) * hs, f64::from(cell_hi) * hs)
            })
            .collect();
        let cells = squares.iter().map(|&(r, lo, _)| (r, lo)).collect();
        tops.push(squares.into_iter().map(|(r, _, hi)| (r, hi)).collect::<Vec<_>>());
        let parts = part_boxes(grid, cache, sb).ok_or(Skipped::TileMissing)?;
        swept.push(SweptBlock {
            rect: rect(ox, oz, size),
            range: [f64::from(lo) * hs, f64::from(hi) * hs],
            cells,
            parts: parts.iter().map(|pb| part_of(pb, anchor, (sx, sz), hs)).collect(),
        });
    }
    let culled: Vec<(Rect, f64)> = culled
        .iter()
        .map(|&(lod, bx, bz, min)| {
            let size = (grid.block_quads << lod) as i64;
            (rect(i64::from(bx) * size, i64::from(bz) * size, size), f64::from(min) * hs)
        })
        .collect();
    // The highest drawn point over an area: its squares' that meet it.
    let meets = |a: &Rect, b: &Rect| a.x0 <= b.x1 && a.x1 >= b.x0 && a.z0 <= b.z1 && a.z1 >= b.z0;
    let top_over = |i: usize, area: &Rect| {
        let squares: &Vec<(Rect, f64)> = &tops[i];
        squares.iter().filter(|(r, _)| meets(r, area)).map(|&(_, hi)| hi).fold(f64::NEG_INFINITY, f64::max)
    };
    let frame =
        SweptFrame { extent, blocks: &swept, culled: &culled, all_parts: layout.all_parts(), top_over: &top_over };
    crate::lod::occlusion::sweep(cam, &frame, rule)
}

/// Occlusion culling of a frame's `blocks` ([`hidden_parts`]): the hidden parts of each
/// are left out (`DrawBlock::hidden_parts`), and blocks hidden whole are not drawn; says
/// what it did, and each block's hidden parts in `masks` (empty when skipped).
pub fn cull(
    grid: &Grid,
    cache: &HostCache,
    view: ([i64; 2], &Camera),
    (blocks, culled): (&mut Vec<StreamedBlock>, &[CulledBlock]),
    drawable: &dyn Fn(TileKey) -> bool,
    (rule, masks_out): (Rule, &mut Vec<u16>),
) -> OcclusionReport {
    let all = layout(grid).all_parts();
    let mut report = OcclusionReport {
        tested: blocks.len(),
        tested_parts: blocks.len() * all.count_ones() as usize,
        ..Default::default()
    };
    match hidden_parts(grid, cache, view, (blocks, culled), drawable, rule) {
        Err(why) => report.skipped = Some(why),
        Ok(masks) => {
            report.hidden = masks.iter().filter(|&&m| m == all).count();
            report.hidden_parts = masks.iter().map(|m| m.count_ones() as usize).sum();
            masks_out.clone_from(&masks);
            let mut masks = masks.into_iter();
            blocks.retain_mut(|b| {
                let m = masks.next().expect("a mask per block");
                b.block.hidden_parts |= m;
                m != all
            });
        }
    }
    report
}
