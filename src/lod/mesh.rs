//! The drawn surface as one triangle mesh, for export: every drawn block's `k x k`
//! vertices where the vertex shader puts them ([`block_vertex`], its CPU mirror: stitched
//! edges, collapsed strips and morph factors applied), in world units, with the shared
//! block index pattern ([`block_mesh_data`]). Triangles beyond the true extent (the
//! margin, whose pixels the renderer discards) are left out.

use crate::lod::block::{block_mesh_data, block_vertex, BlockLayout, DrawBlock};
use crate::lod::heightfield::Heightfield;

/// Positions (world units) and triangle indices of the drawn surface.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct DrawnMesh {
    pub positions: Vec<[f32; 3]>,
    pub indices: Vec<u32>,
    /// Triangles of drawn blocks left out because a vertex lies beyond the true extent.
    pub beyond_extent: usize,
}

impl DrawnMesh {
    pub fn triangles(&self) -> usize {
        self.indices.len() / 3
    }
}

/// The mesh of `blocks` as drawn.
pub fn drawn_mesh(hf: &Heightfield, layout: &BlockLayout, blocks: &[DrawBlock]) -> DrawnMesh {
    let k = layout.k();
    let (_, pattern) = block_mesh_data(k);
    let per_block = (k * k) as usize;
    let mut mesh = DrawnMesh {
        positions: Vec::with_capacity(blocks.len() * per_block),
        indices: Vec::with_capacity(blocks.len() * pattern.len()),
        beyond_extent: 0,
    };
    let (last_x, last_z) = (hf.width as i64 - 1, hf.height as i64 - 1);
    let mut inside = vec![false; per_block];
    for b in blocks {
        let base = mesh.positions.len() as u32;
        for v in 0..k {
            for u in 0..k {
                let (sx, sz, raw) = block_vertex(hf, layout, b, u, v);
                inside[(v * k + u) as usize] = sx <= last_x && sz <= last_z;
                mesh.positions.push(hf.world_position(sx, sz, raw).to_array());
            }
        }
        for t in pattern.chunks_exact(3) {
            if t.iter().all(|&i| inside[i as usize]) {
                mesh.indices.extend(t.iter().map(|&i| base + i));
            } else {
                mesh.beyond_extent += 1;
            }
        }
    }
    mesh
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::lod::heightfield::test_field;

    /// One block at LOD 0 over a 9 x 9 field is the field itself: 64 quads, 128
    /// triangles, every vertex at its sample; a 7 x 5 field in the same grid keeps only
    /// the triangles inside its extent.
    #[test]
    fn one_block_is_the_field() {
        let hf = test_field(9, 9, |x, z| (x * 10 + z) as f32);
        let layout = BlockLayout::of(&hf, 9).unwrap();
        let b = DrawBlock::new(0, 0, 0);
        let m = drawn_mesh(&hf, &layout, &[b]);
        assert_eq!((m.positions.len(), m.triangles(), m.beyond_extent), (81, 128, 0));
        assert_eq!(m.positions[9 * 3 + 2], [2.0, 23.0, 3.0]);
        let small = test_field(7, 5, |x, z| (x + z) as f32);
        let m = drawn_mesh(&small, &layout, &[b]);
        assert_eq!((m.triangles(), m.beyond_extent), (6 * 4 * 2, 128 - 48));
    }
}
