//! A streamed frame's blocks as the vertex shader draws them (SPEC sections 5 and 8):
//! each selected block with its coarser neighbours' strides and resolved corners, read
//! from the tiles the frame holds, and the atlas layer its heights come from. The
//! stitching is the in-memory traversal's own ([`stitch_blocks`]); only where the
//! samples come from ([`Resident`]) and how neighbours are found ([`SparseLods`]) differ.

pub use super::cache::{layout, Resident};
use super::cache::{HostCache, SUB};
use super::traverse::{square_of_samples_box, Selection};
use super::{Grid, TileKey};
use crate::lod::block::{part_boxes_by, DrawBlock, PartBox, PART_FRUSTUM_MARGIN_PX};
use crate::lod::camera::Camera;
use crate::lod::traversal::{stitch_blocks, SparseLods};

/// A block to draw and where its heights are: the tile it is drawn from.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct StreamedBlock {
    pub block: DrawBlock,
    pub tile: TileKey,
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
    blocks.into_iter().zip(&sel.blocks).map(|(block, s)| StreamedBlock { block, tile: s.tile }).collect()
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
