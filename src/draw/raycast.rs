//! Which blocks a frame ray-casts instead of rasterizing (SPEC 10, seed 003).
//!
//! A ray-cast block is drawn by `raycast.vert`/`raycast.frag`: its bounding box, whose
//! pixels each cast a ray through the triangles the block's rasterized self would draw,
//! and write the hit's depth (deferred shading then shades it as any other pixel). The
//! shader intersects the block's own vertices and resolved corners along the a-i
//! diagonal; it does not morph or follow a coarser neighbour's edge, so only blocks that
//! do neither are eligible. Their error and their edges are then the rasterized block's.

use crate::lod::block::{BlockLayout, DrawBlock, MORPH_ONE};

/// Which blocks are ray-cast.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, clap::ValueEnum)]
pub enum Raycast {
    /// None: every block is rasterized.
    #[default]
    Off,
    /// Every other eligible block, as on a checkerboard (the crack check of SPEC 10).
    Checkerboard,
    /// Every eligible block (to measure the ray-caster's cost against the rasterizer's).
    All,
}

/// Whether `b` can be ray-cast: it does not morph, no edge follows a coarser neighbour,
/// and it lies inside the true extent `[0, extent - 1]` (the rasterizer clips the
/// embedding margin; the ray-caster does not).
pub fn eligible(layout: &BlockLayout, b: &DrawBlock, extent: [u32; 2]) -> bool {
    let (ox, oz) = b.origin(layout);
    let side = layout.block_samples(b.lod);
    b.coarser == [0; 4]
        && b.morph == MORPH_ONE
        && b.edge_morph == [MORPH_ONE; 4]
        && ox + side < extent[0]
        && oz + side < extent[1]
}

/// Whether `mode` ray-casts `b`.
pub fn chosen(mode: Raycast, layout: &BlockLayout, b: &DrawBlock, extent: [u32; 2]) -> bool {
    match mode {
        Raycast::Off => false,
        Raycast::Checkerboard => (b.bx + b.bz).is_multiple_of(2) && eligible(layout, b, extent),
        Raycast::All => eligible(layout, b, extent),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn layout() -> BlockLayout {
        BlockLayout { n: 6, m: 5, roots: [1, 1] }
    }

    #[test]
    fn only_plain_blocks_inside_the_extent_are_eligible() {
        let l = layout();
        let plain = DrawBlock::new(0, 0, 0);
        assert!(eligible(&l, &plain, [65, 65]));
        // The block's far edge (sample 32) must lie inside the extent.
        assert!(!eligible(&l, &plain, [32, 65]));
        assert!(eligible(&l, &plain, [33, 33]));
        let mut stitched = plain;
        stitched.coarser[2] = 2;
        assert!(!eligible(&l, &stitched, [65, 65]));
        let mut morphing = plain;
        morphing.morph = MORPH_ONE - 1;
        assert!(!eligible(&l, &morphing, [65, 65]));
        let mut edge = plain;
        edge.edge_morph[3] = 0;
        assert!(!eligible(&l, &edge, [65, 65]));
        assert!(chosen(Raycast::Checkerboard, &l, &plain, [65, 65]));
        assert!(!chosen(Raycast::Checkerboard, &l, &DrawBlock::new(0, 1, 0), [65, 65]));
        assert!(!chosen(Raycast::Off, &l, &plain, [65, 65]));
    }
}
