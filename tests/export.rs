//! `render --export-mesh FILE.glb`: the drawn mesh as binary glTF. Read back with the
//! `gltf` crate (an independent reader and validator), the file's triangles are the
//! surface the renderer draws: at every sample of the true extent their height is the
//! audit's rendered surface (stitched, collapsed, morphed), and the command's file has
//! exactly the triangles the frame drew.

mod common;
use common::*;
use glam::Vec3;
use std::process::Command;
use vkterrain::app::export::glb_bytes;
use vkterrain::app::outputs::TerrainFacts;
use vkterrain::lod::audit::rendered_raw;
use vkterrain::lod::block::{BlockLayout, MORPH_ONE};
use vkterrain::lod::camera::Camera;
use vkterrain::lod::gie::{block_errors, group_errors, ErrorMode, ErrorParams};
use vkterrain::lod::heightfield::Heightfield;
use vkterrain::lod::mesh::drawn_mesh;
use vkterrain::lod::pyramid::MinMaxPyramid;
use vkterrain::lod::traversal::{traverse, BlockCaches, LodSelect};

/// Positions and indices of the one primitive in a GLB, through the `gltf` crate.
fn read_glb(bytes: &[u8]) -> (Vec<[f32; 3]>, Vec<u32>, serde_json::Value) {
    let g = gltf::Gltf::from_slice(bytes).expect("a valid GLB");
    let blob = g.blob.as_deref().expect("a binary chunk");
    let mesh = g.meshes().next().expect("one mesh");
    let prim = mesh.primitives().next().expect("one primitive");
    assert_eq!(prim.mode(), gltf::mesh::Mode::Triangles);
    let reader = prim.reader(|_| Some(blob));
    let positions: Vec<[f32; 3]> = reader.read_positions().expect("positions").collect();
    let indices: Vec<u32> = reader.read_indices().expect("indices").into_u32().collect();
    let extras = g.scenes().next().and_then(|s| s.extras().as_ref().map(|r| serde_json::from_str(r.get()).unwrap()));
    (positions, indices, extras.unwrap_or_default())
}

/// Heights of the exported triangles at every integer sample they cover (in sample
/// coordinates from the world x and z), with every covering triangle agreeing.
fn mesh_heights(hf: &Heightfield, pos: &[[f32; 3]], idx: &[u32]) -> Vec<Option<f32>> {
    let mut h: Vec<Option<f32>> = vec![None; hf.width * hf.height];
    assert_eq!(idx.len() % 3, 0);
    for t in idx.chunks_exact(3) {
        let p: Vec<[f64; 3]> = t
            .iter()
            .map(|&i| {
                let v = pos[i as usize];
                [v[0] as f64 / hf.spacing.x as f64, v[1] as f64, v[2] as f64 / hf.spacing.z as f64]
            })
            .collect();
        let area = (p[1][0] - p[0][0]) * (p[2][2] - p[0][2]) - (p[2][0] - p[0][0]) * (p[1][2] - p[0][2]);
        if area.abs() < 1e-9 {
            continue; // a collapsed (degenerate) triangle covers nothing
        }
        let (x0, x1) =
            (p.iter().map(|v| v[0]).fold(f64::MAX, f64::min), p.iter().map(|v| v[0]).fold(f64::MIN, f64::max));
        let (z0, z1) =
            (p.iter().map(|v| v[2]).fold(f64::MAX, f64::min), p.iter().map(|v| v[2]).fold(f64::MIN, f64::max));
        for z in z0.round() as i64..=z1.round() as i64 {
            for x in x0.round() as i64..=x1.round() as i64 {
                let (px, pz) = (x as f64, z as f64);
                let w1 = ((px - p[0][0]) * (p[2][2] - p[0][2]) - (p[2][0] - p[0][0]) * (pz - p[0][2])) / area;
                let w2 = ((p[1][0] - p[0][0]) * (pz - p[0][2]) - (px - p[0][0]) * (p[1][2] - p[0][2])) / area;
                let w0 = 1.0 - w1 - w2;
                if w0 < -1e-6 || w1 < -1e-6 || w2 < -1e-6 || x >= hf.width as i64 || z >= hf.height as i64 {
                    continue;
                }
                let y = (w0 * p[0][1] + w1 * p[1][1] + w2 * p[2][1]) as f32;
                let cell = &mut h[z as usize * hf.width + x as usize];
                if let Some(prev) = *cell {
                    assert!(
                        (prev - y).abs() <= 1e-3 * prev.abs().max(1.0),
                        "sample ({x}, {z}): {prev} and {y}: a crack"
                    );
                }
                *cell = Some(y);
            }
        }
    }
    h
}

/// An anisotropic field with ridges and a spike, seen low and at an angle so that the
/// frame has several LODs, stitched edges and morphing blocks: the GLB's surface is the
/// rendered surface at every covered sample, and covers every sample of every drawn block.
#[test]
fn the_glb_is_the_drawn_surface() {
    let hf = field(129, 97, [3.0, 1.25], |x, z| {
        (x as f32 * 0.06).sin() * (z as f32 * 0.05).cos() * 10.0 + if (x, z) == (70, 40) { 30.0 } else { 0.0 }
    });
    let mm = MinMaxPyramid::build(&hf);
    let layout = BlockLayout::of(&hf, 9).unwrap();
    let eye = Vec3::new(20.0 * 3.0, 40.0, 10.0 * 1.25);
    let cam = Camera::look_at(eye, Vec3::new(100.0 * 3.0, 0.0, 80.0 * 1.25), 60.0, 640, 480, 0.05);
    let errors = block_errors(&group_errors(&hf, &mm, &ErrorParams::new(&cam, ErrorMode::Strict)), layout.m);
    let t = traverse(
        &hf,
        &mm,
        &BlockCaches::default(),
        &layout,
        &cam,
        LodSelect::errors(&errors, cam.position, 1.0, ErrorMode::Strict),
    );
    let lods: std::collections::BTreeSet<u32> = t.blocks.iter().map(|b| b.lod).collect();
    assert!(lods.len() >= 3, "LODs drawn: {lods:?}");
    assert!(t.blocks.iter().any(|b| b.coarser.iter().any(|&c| c > 0)), "no stitched edge");
    let morphing =
        t.blocks.iter().filter(|b| b.morph != MORPH_ONE || b.edge_morph.iter().any(|&m| m != MORPH_ONE)).count();
    assert!(morphing > 0, "no morphing block");
    let mesh = drawn_mesh(&hf, &layout, &t.blocks);
    let (pos, idx, extras) = read_glb(&glb_bytes(&mesh, &TerrainFacts::of(&hf)));
    assert_eq!((pos.len(), idx.len()), (mesh.positions.len(), mesh.indices.len()));
    assert_eq!(extras["terrain"]["spacing_m"], serde_json::json!([3.0, 1.25]));
    let heights = mesh_heights(&hf, &pos, &idx);
    let mut compared = 0;
    for b in &t.blocks {
        let (ox, oz) = b.origin(&layout);
        let side = layout.block_samples(b.lod) as usize;
        for z in oz as usize..(oz as usize + side + 1).min(hf.height) {
            for x in ox as usize..(ox as usize + side + 1).min(hf.width) {
                let want =
                    rendered_raw(&hf, &layout, b, x as i64, z as i64).expect("inside the block") * hf.height_scale;
                let got =
                    heights[z * hf.width + x].unwrap_or_else(|| panic!("sample ({x}, {z}) of block {b:?} not covered"));
                assert!(
                    (got - want).abs() <= 1e-3 * want.abs().max(1.0),
                    "sample ({x}, {z}): mesh {got}, drawn {want}"
                );
                compared += 1;
            }
        }
    }
    // The frustum culls part of the field; most of it is on screen.
    assert!(compared > hf.width * hf.height / 2, "compared only {compared} samples");
}

/// The command end to end: `render --export-mesh` writes a GLB with the frame's
/// triangles (all of them, the field being `2^n + 1` a side) and the terrain's facts.
#[test]
fn render_exports_the_mesh() {
    let dir = TempDir::new("export");
    let f = dir.path().join("hills.f32");
    let bytes: Vec<u8> = (0..129 * 129)
        .flat_map(|i| ((((i % 129) as f32 * 0.2).sin() * ((i / 129) as f32 * 0.17).cos()) * 20.0).to_le_bytes())
        .collect();
    std::fs::write(&f, bytes).unwrap();
    let glb = dir.path().join("mesh.glb");
    let out = Command::new(env!("CARGO_BIN_EXE_vkterrain"))
        .args([
            "render",
            "--heightmap",
            f.to_str().unwrap(),
            "--raw-size",
            "129x129",
            "--spacing",
            "2,3",
            "--height-scale",
            "1",
        ])
        .args(["--camera", "20,60,30", "--look-at", "200,0,300", "--size", "320x240", "--validation", "on"])
        .args(["--out", dir.path().join("frame.png").to_str().unwrap(), "--export-mesh", glb.to_str().unwrap()])
        .output()
        .unwrap();
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(out.status.success(), "{stderr}");
    let j: serde_json::Value = serde_json::from_slice(&out.stdout).expect("JSON on stdout");
    assert_eq!(j["validation_messages"], 0, "{stderr}");
    let (pos, idx, extras) = read_glb(&std::fs::read(&glb).unwrap());
    assert_eq!(idx.len() as u64 / 3, j["mesh_triangles"].as_u64().unwrap());
    assert_eq!(j["mesh_triangles_beyond_extent"], 0);
    // The file holds the drawn blocks whole: the triangles rasterized and the parts left
    // out of them (here outside the frustum: the camera sees part of the field).
    let hidden = j["hidden_triangles"].as_u64().unwrap();
    assert!(j["hidden_parts"].as_u64().unwrap() > 0 && hidden > 0, "{j}");
    assert_eq!(
        j["mesh_triangles"].as_u64().unwrap(),
        j["triangles"].as_u64().unwrap() + hidden,
        "the file holds every triangle drawn and every hidden part"
    );
    assert_eq!(pos.len() as u64, j["mesh_vertices"].as_u64().unwrap());
    assert_eq!(extras["terrain"]["spacing_m"], serde_json::json!([2.0, 3.0]));
    // Every vertex lies over the terrain's extent, and every triangle that is not
    // collapsed faces up (counter-clockwise seen from +y: glTF's front face).
    assert!(pos.iter().all(|p| (0.0..=256.0).contains(&p[0]) && (0.0..=384.0).contains(&p[2])));
    let mut up = 0;
    for t in idx.chunks_exact(3) {
        let [a, b, c] = [0, 1, 2].map(|j| Vec3::from(pos[t[j] as usize]));
        let n = (b - a).cross(c - a);
        if n.length() > 1e-6 {
            assert!(n.y > 0.0, "triangle {t:?} faces down");
            up += 1;
        }
    }
    assert!(up > idx.len() / 6, "{up} triangles checked");
    // A wrong extension is refused before anything runs.
    let bad = Command::new(env!("CARGO_BIN_EXE_vkterrain"))
        .args(["render", "--out", dir.path().join("x.png").to_str().unwrap(), "--export-mesh", "mesh.obj"])
        .output()
        .unwrap();
    assert_eq!(bad.status.code(), Some(2), "{}", String::from_utf8_lossy(&bad.stderr));
    assert!(String::from_utf8_lossy(&bad.stderr).contains(".glb"));
}

/// `render --stream --export-mesh`: the streamed frame's mesh from the tiles it held, as
/// in memory: every drawn triangle and every part left out (outside the frustum) in the
/// file, a watertight surface over every sample it covers (no two triangles disagree),
/// within the archive's heights, facing up, with the terrain's facts in its extras.
#[test]
fn a_streamed_render_exports_its_mesh() {
    let dir = TempDir::new("export-streamed");
    let archive = dir.path().join("s.pmtiles");
    let a = archive.to_str().unwrap();
    let o = Command::new(env!("CARGO_BIN_EXE_vkterrain"))
        .args(["prepare", "--synthetic", "1025", "--out", a])
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let glb = dir.path().join("s.glb");
    let out = Command::new(env!("CARGO_BIN_EXE_vkterrain"))
        .args(["render", "--heightmap", a, "--stream", "--validation", "on", "--size", "320x240"])
        .args(["--camera", "1500,900,16000", "--look-at", "15000,300,15000"])
        .args(["--out", dir.path().join("s.png").to_str().unwrap(), "--export-mesh", glb.to_str().unwrap()])
        .output()
        .unwrap();
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(out.status.success(), "{stderr}");
    let j: serde_json::Value = serde_json::from_slice(&out.stdout).expect("JSON on stdout");
    assert_eq!((j["streamed"].as_bool(), j["gpu"]["validation_messages"].as_u64()), (Some(true), Some(0)), "{j}");
    let (pos, idx, extras) = read_glb(&std::fs::read(&glb).unwrap());
    assert_eq!(idx.len() as u64 / 3, j["mesh_triangles"].as_u64().unwrap());
    assert_eq!(pos.len() as u64, j["mesh_vertices"].as_u64().unwrap());
    let hidden = j["hidden_triangles"].as_u64().unwrap();
    assert!(hidden > 0, "the view leaves parts outside the frustum: {j}");
    // Blocks occlusion culling hid whole are in the file too (2,048 triangles each).
    let occluded = j["occlusion"]["hidden"].as_u64().unwrap() * 2048;
    assert_eq!(
        j["mesh_triangles"].as_u64().unwrap() + j["mesh_triangles_beyond_extent"].as_u64().unwrap(),
        j["triangles"].as_u64().unwrap() + hidden + occluded,
        "the file holds every triangle drawn, every part left out and every block hidden: {j}"
    );
    assert_eq!(extras["terrain"]["samples"], serde_json::json!([1025, 1025]));
    // The archive's heights, in memory, bound the surface; mesh_heights asserts that no
    // two triangles over a sample disagree (a crack) and gives the covered samples.
    let hf = vkterrain::input::archive::Archive::open(&archive).unwrap().heightfield().unwrap();
    let (lo, hi) = hf.raw.iter().fold((f32::MAX, f32::MIN), |(a, b), &v| (a.min(v), b.max(v)));
    let scale = hf.height_scale;
    assert!(
        pos.iter().all(|p| p[1] >= lo * scale - 1e-3 && p[1] <= hi * scale + 1e-3),
        "heights outside the archive's"
    );
    let covered = mesh_heights(&hf, &pos, &idx).iter().filter(|h| h.is_some()).count();
    assert!(covered > 100_000, "{covered} samples covered");
    for t in idx.chunks_exact(3) {
        let [a, b, c] = [0, 1, 2].map(|j| Vec3::from(pos[t[j] as usize]));
        let n = (b - a).cross(c - a);
        assert!(n.length() <= 1e-6 || n.y > 0.0, "triangle {t:?} faces down");
    }
}
