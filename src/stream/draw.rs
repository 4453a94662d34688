//! A streamed frame's blocks as the vertex shader draws them (SPEC sections 5 and 8):
//! each selected block with its coarser neighbours' strides and resolved corners, read
//! from the tiles the frame holds, and the atlas layer its heights come from. The
//! stitching is the in-memory traversal's own ([`stitch_blocks`]); only where the
//! samples come from ([`Resident`]) and how neighbours are found ([`SparseLods`]) differ.

use super::cache::HostCache;
pub use super::cache::{layout, Resident};
use super::traverse::Selection;
use super::{Grid, TileKey};
use crate::lod::block::DrawBlock;
use crate::lod::traversal::{stitch_blocks, SparseLods};

/// A block to draw and where its heights are: the tile it is drawn from.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct StreamedBlock {
    pub block: DrawBlock,
    pub tile: TileKey,
}

/// The blocks of `sel` stitched to each other (unmorphed: streamed frames do not
/// geomorph yet), with the tiles they are drawn from: as the selection stitched them, or
/// (a selection made without the stitching rule) stitched here.
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
