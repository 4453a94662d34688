//! A streamed frame's blocks as the vertex shader draws them (SPEC sections 5 and 8):
//! each selected block with its coarser neighbours' strides and resolved corners, read
//! from the tiles the frame holds, and the atlas layer its heights come from. The
//! stitching is the in-memory traversal's own ([`stitch_selection`]); only where the
//! samples come from differs ([`Resident`]).

use super::cache::{root_lod, HostCache, BLOCK_QUADS};
use super::traverse::Selection;
use super::{Grid, TileKey};
use crate::lod::block::{BlockLayout, DrawBlock};
use crate::lod::heightfield::RawSamples;
use crate::lod::traversal::stitch_selection;

/// The block layout of an archive's grid: blocks of `BLOCK_QUADS + 1` vertices, one
/// root block over each top-level tile.
pub fn layout(grid: &Grid) -> BlockLayout {
    let m = BLOCK_QUADS.trailing_zeros();
    let [nx, nz] = grid.tiles_at(grid.top);
    BlockLayout { n: root_lod(grid) + m, m, roots: [nx as usize, nz as usize] }
}

/// The samples of the tiles a cache holds, at integer sample coordinates: a sample is
/// read from the finest held tile whose vertices include it. Every level holds the same
/// value at a sample (tiles are subsampled, not filtered; beyond the true extent they
/// repeat its edge at every level), so this is the value the shader fetches from the
/// block's own tile. `NaN` where no held tile has the sample: a drawn block never asks
/// for one (its tile and its coarser neighbours' are held), and tests look for it.
pub struct Resident<'a> {
    pub grid: &'a Grid,
    pub cache: &'a HostCache,
}

impl RawSamples for Resident<'_> {
    fn raw_at(&self, x: i64, z: i64) -> f32 {
        if x < 0 || z < 0 {
            return f32::NAN;
        }
        let finest = (x.trailing_zeros().min(z.trailing_zeros()) as u8).min(self.grid.top);
        for level in (0..=finest).rev() {
            let span = self.grid.tile_span(level) as i64;
            // A sample on a tile border is in both tiles; either will do.
            let candidates = |c: i64| [Some(c / span), (c % span == 0 && c > 0).then(|| c / span - 1)];
            for tz in candidates(z).into_iter().flatten() {
                for tx in candidates(x).into_iter().flatten() {
                    let key = TileKey::new(level, tx as u32, tz as u32);
                    if let Some(tile) = self.cache.peek(key) {
                        let (i, j) = ((x - tx * span) >> level, (z - tz * span) >> level);
                        return tile.vertex(i as usize, j as usize);
                    }
                }
            }
        }
        f32::NAN
    }
}

/// A block to draw and where its heights are: the tile it is drawn from.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct StreamedBlock {
    pub block: DrawBlock,
    pub tile: TileKey,
}

/// The blocks of `sel` stitched to each other (unmorphed: streamed frames do not
/// geomorph yet), with the tiles they are drawn from.
pub fn stitched_blocks(grid: &Grid, cache: &HostCache, sel: &Selection) -> Vec<StreamedBlock> {
    let mut blocks: Vec<DrawBlock> = sel.blocks.iter().map(|b| DrawBlock::new(b.lod, b.bx, b.bz)).collect();
    stitch_selection(&Resident { grid, cache }, &layout(grid), &mut blocks);
    blocks.into_iter().enumerate().map(|(i, block)| StreamedBlock { block, tile: sel.blocks[i].tile }).collect()
}
