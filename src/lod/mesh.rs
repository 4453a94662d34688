//! The drawn surface as one triangle mesh, for export: every drawn block's `k x k`
//! vertices where the vertex shader puts them ([`block_vertex`], its CPU mirror: stitched
//! edges, collapsed strips and morph factors applied), in world units, with the shared
//! block index pattern ([`block_mesh_data`]), wound counter-clockwise seen from above
//! (glTF's front faces; the renderer draws both sides). Left out, as the renderer leaves
//! their pixels out: triangles beyond the true extent (the margin), and with `--voids
//! hole` those whose centre lies in a hole (the shader's rule, at the centre); the
//! vertices only those triangles use go too.

use crate::lod::block::{block_mesh_data, block_vertex, BlockLayout, DrawBlock};
use crate::lod::heightfield::{Heightfield, RawSamples};

/// Positions (world units) and triangle indices of the drawn surface.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct DrawnMesh {
    pub positions: Vec<[f32; 3]>,
    pub indices: Vec<u32>,
    /// Triangles of drawn blocks left out because a vertex lies beyond the true extent.
    pub beyond_extent: usize,
    /// Triangles left out because their centre lies in a hole (`--voids hole`).
    pub in_holes: usize,
}

impl DrawnMesh {
    pub fn triangles(&self) -> usize {
        self.indices.len() / 3
    }
}

/// The mesh of `blocks` as drawn.
pub fn drawn_mesh(hf: &Heightfield, layout: &BlockLayout, blocks: &[DrawBlock]) -> DrawnMesh {
    let hole = |x: i64, z: i64| hf.is_hole(x, z);
    let surface = MeshSurface {
        last: [hf.width as i64 - 1, hf.height as i64 - 1],
        world: &|x, z, raw| hf.world_position(x, z, raw).to_array(),
        hole: hf.void_mask.is_some().then_some(&hole as &dyn Fn(i64, i64) -> bool),
    };
    drawn_mesh_of(hf, layout, blocks, &surface)
}

/// Where a terrain's samples are, for [`drawn_mesh_of`]: its last sample along x and z
/// (the true extent), world positions of samples, and its holes (`--voids hole`).
pub struct MeshSurface<'a> {
    pub last: [i64; 2],
    pub world: &'a dyn Fn(i64, i64, f32) -> [f32; 3],
    pub hole: Option<&'a dyn Fn(i64, i64) -> bool>,
}

/// [`drawn_mesh`] over samples from anywhere (a heightfield in memory, a streamed
/// frame's held tiles).
pub fn drawn_mesh_of<S: RawSamples + ?Sized>(
    samples: &S,
    layout: &BlockLayout,
    blocks: &[DrawBlock],
    surface: &MeshSurface,
) -> DrawnMesh {
    let k = layout.k();
    let (_, pattern) = block_mesh_data(k);
    let per_block = (k * k) as usize;
    let mut mesh = DrawnMesh::default();
    let [last_x, last_z] = surface.last;
    // Block-local vertices: sample position, world position, inside the true extent.
    let mut local: Vec<((i64, i64), [f32; 3], bool)> = Vec::with_capacity(per_block);
    // Index of each block vertex in the mesh, once a kept triangle uses it.
    let mut index = vec![u32::MAX; per_block];
    for b in blocks {
        local.clear();
        index.fill(u32::MAX);
        for v in 0..k {
            for u in 0..k {
                let (sx, sz, raw) = block_vertex(samples, layout, b, u, v);
                local.push(((sx, sz), (surface.world)(sx, sz, raw), sx <= last_x && sz <= last_z));
            }
        }
        for t in pattern.chunks_exact(3) {
            if !t.iter().all(|&i| local[i as usize].2) {
                mesh.beyond_extent += 1;
                continue;
            }
            if surface.hole.is_some_and(|hole| in_hole(hole, t.iter().map(|&i| local[i as usize].0))) {
                mesh.in_holes += 1;
                continue;
            }
            // The block pattern is clockwise seen from above: a, i, c instead of a, c, i.
            for &i in [t[0], t[2], t[1]].iter() {
                let i = i as usize;
                if index[i] == u32::MAX {
                    index[i] = mesh.positions.len() as u32;
                    mesh.positions.push(local[i].1);
                }
                mesh.indices.push(index[i]);
            }
        }
    }
    mesh
}

/// The shader's hole rule (`terrain_shade.glsl::in_hole`) at a triangle's centre: the
/// bilinear share of hole samples around it is at least one half.
fn in_hole(is_hole: &dyn Fn(i64, i64) -> bool, corners: impl Iterator<Item = (i64, i64)>) -> bool {
    let (mut x, mut z) = (0.0f64, 0.0f64);
    for (sx, sz) in corners {
        x += sx as f64 / 3.0;
        z += sz as f64 / 3.0;
    }
    let (x0, z0) = (x.floor() as i64, z.floor() as i64);
    let (fx, fz) = (x - x0 as f64, z - z0 as f64);
    let h = |dx: i64, dz: i64| is_hole(x0 + dx, z0 + dz) as u8 as f64;
    let share = (h(0, 0) * (1.0 - fx) + h(1, 0) * fx) * (1.0 - fz) + (h(0, 1) * (1.0 - fx) + h(1, 1) * fx) * fz;
    share >= 0.5
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
        assert!(m.positions.contains(&[2.0, 23.0, 3.0]));
        // Counter-clockwise seen from above: every normal points up.
        for t in m.indices.chunks_exact(3) {
            let [a, b, c] = [0, 1, 2].map(|j| glam::Vec3::from(m.positions[t[j] as usize]));
            assert!((b - a).cross(c - a).y > 0.0, "triangle {t:?} faces down");
        }
        // A 13 x 10 field in a 13 x 13 grid: the margin's triangles and the vertices only
        // they use go.
        let small = test_field(13, 10, |x, z| (x + z) as f32);
        let layout = BlockLayout::of(&small, 5).unwrap();
        let [bx, bz] = layout.blocks(0);
        let blocks: Vec<DrawBlock> =
            (0..bz as u32).flat_map(|z| (0..bx as u32).map(move |x| DrawBlock::new(0, x, z))).collect();
        let m = drawn_mesh(&small, &layout, &blocks);
        assert_eq!(small.grid(), [13, 13]);
        assert_eq!((m.triangles(), m.beyond_extent), (12 * 9 * 2, 12 * 12 * 2 - 12 * 9 * 2));
        assert!(m.positions.iter().all(|p| p[2] <= 9.0), "a margin vertex is left in");
    }

    /// With holes, the triangles whose centre is in a hole are left out, and their
    /// vertices with them.
    #[test]
    fn holes_are_left_out() {
        let mut hf = test_field(9, 9, |x, z| (x + z) as f32);
        hf.void_mask = Some((0..81).map(|i| (3..6).contains(&(i % 9)) && (3..6).contains(&(i / 9))).collect());
        let layout = BlockLayout::of(&hf, 9).unwrap();
        let m = drawn_mesh(&hf, &layout, &[DrawBlock::new(0, 0, 0)]);
        assert!(m.in_holes >= 8 && m.in_holes + m.triangles() == 128, "{} in holes", m.in_holes);
        assert!(!m.positions.contains(&[4.0, 8.0, 4.0]), "the hole's centre vertex is left out");
    }
}
