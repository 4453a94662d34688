//! The vertex shader's placement of every vertex of every drawn block (stitching
//! and morphing included) equals its plain-Rust mirror `quadtree::block_vertex`, bit for bit: the
//! GPU side of the crack-free guarantee that `traversal.rs` proves on the CPU.

mod common;
use common::*;
use glam::Vec3;
use std::sync::Arc;
use vkterrain::draw::blocks::{BlocksRenderer, COLOR_FORMAT};
use vkterrain::gpu::terrain::TerrainGpu;
use vkterrain::lod::block::{block_vertex, BlockLayout};
use vkterrain::lod::camera::Camera;
use vkterrain::lod::gie::{block_errors, group_errors, ErrorMode, ErrorParams};
use vkterrain::lod::heightfield::Heightfield;
use vkterrain::lod::pyramid::MinMaxPyramid;
use vkterrain::lod::traversal::{traverse, BlockCaches, LodSelect};

/// Returns (vertices compared, collapsed-edge vertices, on-segment vertices, morphed
/// interior vertices, vertices that follow a coarser neighbour's morphed edge).
fn compare(
    device: &Arc<vkterrain::vk::Device>,
    hf: &Heightfield,
    k: u32,
    cams: &[Camera],
    delta: f32,
) -> (usize, usize, usize, usize, usize) {
    let mm = MinMaxPyramid::build(hf);
    let layout = BlockLayout::of(hf, k).unwrap();
    let terrain = TerrainGpu::new(device, hf, &mm, None, None).unwrap();
    let mut renderer = BlocksRenderer::new(device, hf, &terrain, layout, COLOR_FORMAT, 1, None).unwrap();
    let (mut n, mut collapsed, mut lerped, mut morphed, mut following) = (0, 0, 0, 0, 0);
    for cam in cams {
        let errors = block_errors(&group_errors(hf, &mm, &ErrorParams::new(cam, ErrorMode::Strict)), layout.m);
        let t = traverse(
            hf,
            &mm,
            &BlockCaches::default(),
            &layout,
            cam,
            LodSelect::errors(&errors, cam.position, delta, ErrorMode::Strict),
        );
        let gpu = renderer.capture_vertices(hf, &terrain, cam, &t.blocks).unwrap();
        let kk = layout.k();
        for (i, b) in t.blocks.iter().enumerate() {
            let (ox, oz) = b.origin(&layout);
            for v in 0..kk {
                for u in 0..kk {
                    let (sx, sz, raw) = block_vertex(hf, &layout, b, u, v);
                    let want = hf.world_position(sx, sz, raw).to_array();
                    let got = gpu[i * (kk * kk) as usize + (v * kk + u) as usize];
                    assert_eq!([got[0], got[1], got[2]], want, "block {b:?} vertex ({u},{v})");
                    let moved = (sx, sz) != (ox as i64 + (u * b.stride()) as i64, oz as i64 + (v * b.stride()) as i64);
                    let interior = u > 0 && v > 0 && u < kk - 1 && v < kk - 1;
                    collapsed += moved as usize;
                    lerped += (!moved && !interior && raw != hf.raw_at(sx, sz)) as usize;
                    morphed += (interior && raw != hf.raw_at(sx, sz)) as usize;
                    let coarse_side = (v == 0 && b.coarser[0] > 0)
                        || (u == kk - 1 && b.coarser[1] > 0)
                        || (v == kk - 1 && b.coarser[2] > 0)
                        || (u == 0 && b.coarser[3] > 0);
                    following += (coarse_side && raw != block_vertex(hf, &layout, &b.unmorphed(), u, v).2) as usize;
                    n += 1;
                }
            }
        }
    }
    (n, collapsed, lerped, morphed, following)
}

#[test]
fn vertex_shader_placement_matches_the_cpu_mirror() {
    let device = gpu();
    assert!(device.features.vertex_stores, "this test needs vertexPipelineStoresAndAtomics (lavapipe has it)");
    let hills = field(257, 257, [4.0, 1.5], |x, z| {
        (x as f32 * 0.05).sin() * (z as f32 * 0.07).cos() * 30.0 + if (x * 7 + z * 3) % 61 == 0 { 3.0 } else { 0.0 }
    });
    let cams: Vec<Camera> = (0..4)
        .map(|i| {
            let a = i as f32 * 1.7;
            let pos = Vec3::new(512.0 + 300.0 * a.cos(), 40.0 + 30.0 * i as f32, 512.0 + 300.0 * a.sin());
            Camera::look_at(pos, Vec3::new(512.0, 0.0, 512.0), 60.0, 320, 240, 0.2)
        })
        .collect();
    let (mut total, mut collapsed, mut lerped, mut morphed, mut following) = (0, 0, 0, 0, 0);
    for k in [3, 9, 33] {
        let (n, c, l, m, f) = compare(&device, &hills, k, &cams, 1.0);
        total += n;
        collapsed += c;
        lerped += l;
        morphed += m;
        following += f;
    }
    // A lone spike next to flat ground: LOD differences beyond m (vertices on a segment).
    let lone = field(257, 257, 1.0, |x, z| {
        if (x, z) == (129, 129) {
            50.0
        } else if (x + z) % 9 == 0 {
            0.25
        } else {
            0.0
        }
    });
    let top = [Camera::look_at(Vec3::new(128.0, 300.0, 128.0), Vec3::new(128.0, 0.0, 127.0), 70.0, 320, 240, 0.05)];
    let (n, c, l, m, f) = compare(&device, &lone, 3, &top, 1.0);
    total += n;
    collapsed += c;
    lerped += l;
    morphed += m;
    following += f;
    println!(
        "{total} vertices compared: {collapsed} collapsed onto a coarser neighbour, {lerped} edge vertices off their sample's height, {morphed} interior vertices morphed, {following} following a coarser neighbour's morphed edge"
    );
    assert!(collapsed > 0 && lerped > 0, "both stitching cases must occur ({collapsed}, {lerped})");
    assert!(morphed > 0, "no morphed vertex was compared");
    assert!(following > 0, "no vertex on a morphed coarser edge was compared");
    finish(device);
}
