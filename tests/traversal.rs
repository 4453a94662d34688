//! Traversal, tiling, stitching and the audit of the screen-space guarantee (SPEC
//! sections 5 and 7), in plain Rust with the reference error pyramid (which the GPU
//! matches texel for texel, see gpu_errors.rs).

mod common;
use common::*;
use glam::Vec3;
use vkterrain::audit::{audit, check_tiling};
use vkterrain::camera::Camera;
use vkterrain::gie::{block_errors, group_errors, ErrorMode, ErrorParams};
use vkterrain::heightfield::{self, Heightfield, LoadOptions, MinMaxPyramid};
use vkterrain::quadtree::{block_vertex, traverse, BlockLayout, LodSelect, Traversal};

/// A small deterministic generator (no dependency, reproducible poses).
struct Rng(u64);
impl Rng {
    fn next(&mut self) -> f32 {
        self.0 = self.0.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
        ((self.0 >> 40) as f32) / ((1u64 << 24) as f32)
    }
}

#[derive(Clone, Copy, Debug)]
enum Pose {
    NearGround,
    High,
    LookingDown,
    Horizon,
}

fn pose(hf: &Heightfield, rng: &mut Rng, kind: Pose) -> Camera {
    let (wx, wz) = hf.world_extent();
    let l = wx.max(wz);
    let x = rng.next() * wx;
    let z = rng.next() * wz;
    let ground = hf.surface_height(x, z);
    let yaw = rng.next() * std::f32::consts::TAU;
    let (y, pitch) = match kind {
        Pose::NearGround => (ground + hf.spacing * (0.3 + 3.0 * rng.next()), -0.4 * rng.next()),
        Pose::High => (ground + l * (0.2 + 0.8 * rng.next()), -0.3 - 0.8 * rng.next()),
        Pose::LookingDown => (ground + hf.spacing * (5.0 + 100.0 * rng.next()), -1.5),
        Pose::Horizon => (ground + hf.spacing * (1.0 + 20.0 * rng.next()), 0.05 * (rng.next() - 0.5)),
    };
    let dir = Vec3::new(yaw.cos() * pitch.cos(), pitch.sin(), yaw.sin() * pitch.cos());
    let pos = Vec3::new(x, y, z);
    let size = if rng.next() < 0.5 { (640, 480) } else { (1280, 720) };
    Camera::look_at(pos, pos + dir, 40.0 + 50.0 * rng.next(), size.0, size.1, hf.spacing * 0.05)
}

fn frame(
    hf: &Heightfield,
    mm: &MinMaxPyramid,
    layout: &BlockLayout,
    cam: &Camera,
    computed_at: &Camera,
    mode: ErrorMode,
    delta: f32,
) -> Traversal {
    let p = ErrorParams::new(computed_at, mode);
    let b = block_errors(&group_errors(hf, mm, &p), layout.m);
    traverse(hf, mm, layout, cam, LodSelect::Errors { errors: &b, computed_at: computed_at.position, delta })
}

/// Runs `count` random poses of every kind; returns the worst audited error per mode.
fn audit_poses(hf: &Heightfield, k: u32, count: usize, seed: u64) -> (f32, f32) {
    let mm = MinMaxPyramid::build(hf);
    let layout = BlockLayout::new(hf.n, k).unwrap();
    let mut rng = Rng(seed);
    let kinds = [Pose::NearGround, Pose::High, Pose::LookingDown, Pose::Horizon];
    let (mut worst_strict, mut worst_paper) = (0.0f32, 0.0f32);
    for i in 0..count {
        let kind = kinds[i % 4];
        let cam = pose(hf, &mut rng, kind);
        let delta = [0.5f32, 1.0, 2.0, 5.0][i % 4];
        // Every other frame uses error data computed at a camera up to 20 samples away
        // (stale data): the correction must keep the bound.
        let old = if i % 2 == 0 {
            cam
        } else {
            let mut o = cam;
            o.position += Vec3::new(rng.next() - 0.5, 0.0, rng.next() - 0.5) * 40.0 * hf.spacing;
            o.position.y = o.position.y.max(hf.surface_height(o.position.x, o.position.z) + hf.spacing * 0.3);
            o
        };
        let t = frame(hf, &mm, &layout, &cam, &old, ErrorMode::Strict, delta);
        check_tiling(hf, &mm, &layout, &t.blocks, &cam).unwrap_or_else(|e| panic!("pose {i} ({kind:?}): {e}"));
        let a = audit(hf, &layout, &t, &cam);
        assert_eq!(a.uncovered, 0, "pose {i} ({kind:?}): visible samples not covered");
        assert!(
            a.max_error_px <= delta * 1.01,
            "strict mode, pose {i} ({kind:?}) camera {:?} delta {delta}: audited {} px at {:?}",
            cam.position,
            a.max_error_px,
            a.worst
        );
        worst_strict = worst_strict.max(a.max_error_px / delta);
        let p = frame(hf, &mm, &layout, &cam, &cam, ErrorMode::Paper, delta);
        worst_paper = worst_paper.max(audit(hf, &layout, &p, &cam).max_error_px / delta);
    }
    (worst_strict, worst_paper)
}

#[test]
fn strict_mode_holds_delta_on_real_data() {
    let hf = heightfield::load(&data("puget_sound/ps_height_1k.png"), &LoadOptions::default()).unwrap();
    let (strict, paper) = audit_poses(&hf, 33, 200, 7);
    println!("Puget Sound 1k, 200 poses: worst audited error / delta: strict {strict:.3}, paper {paper:.3}");
    let hf = heightfield::load(&data("srtm3/mt_fuji_90m.tif"), &LoadOptions::default()).unwrap();
    let (strict, paper) = audit_poses(&hf, 17, 40, 11);
    println!("Mt Fuji SRTM3, 40 poses: worst audited error / delta: strict {strict:.3}, paper {paper:.3}");
}

#[test]
fn strict_mode_holds_delta_on_crafted_fields() {
    let spikes =
        field(257, 257, 4.0, |x, z| if (x * 7 + z * 13) % 97 == 0 { 6.0 } else { ((x as f32) * 0.05).sin() * 4.0 });
    let (s, p) = audit_poses(&spikes, 9, 100, 3);
    println!("spikes: strict {s:.3}, paper {p:.3}");
    let ridges = field(200, 131, 2.0, |x, z| ((x as f32 * 0.2).sin() * (z as f32 * 0.15).cos()).abs() * 25.0);
    let (s, p) = audit_poses(&ridges, 5, 100, 5);
    println!("ridges (non-square): strict {s:.3}, paper {p:.3}");
}

/// Every drawn edge vertex lies on the neighbour's surface: for LOD differences up to m
/// it coincides with one of the neighbour's vertices (same sample, same height).
#[test]
fn stitching_matches_coarser_neighbours() {
    let hf = field(257, 257, 4.0, |x, z| {
        (x as f32 * 0.05).sin() * (z as f32 * 0.07).cos() * 30.0 + if (x * 7 + z * 3) % 61 == 0 { 3.0 } else { 0.0 }
    });
    let mm = MinMaxPyramid::build(&hf);
    let mut seen = std::collections::BTreeSet::new();
    for k in [3u32, 5, 9, 17] {
        let layout = BlockLayout::new(hf.n, k).unwrap();
        let mut rng = Rng(k as u64);
        for i in 0..60 {
            let cam = pose(&hf, &mut rng, [Pose::NearGround, Pose::LookingDown, Pose::Horizon][i % 3]);
            let t = frame(&hf, &mm, &layout, &cam, &cam, ErrorMode::Strict, [0.3f32, 1.0, 4.0][i % 3]);
            for b in &t.blocks {
                for (edge, &ns) in b.coarser.iter().enumerate() {
                    if ns == 0 {
                        continue;
                    }
                    let ratio = ns / b.stride();
                    seen.insert(ratio.trailing_zeros());
                    let kk = layout.k();
                    for t_ in 0..kk {
                        let (u, v) = match edge {
                            0 => (t_, 0),
                            1 => (kk - 1, t_),
                            2 => (t_, kk - 1),
                            _ => (0, t_),
                        };
                        let (sx, sz, raw) = block_vertex(&hf, &layout, b, u, v);
                        let along = if edge % 2 == 0 { sx } else { sz };
                        if ns <= (kk - 1) * b.stride() {
                            // Collapsed onto a neighbour vertex: same sample, exact height.
                            assert_eq!(
                                along % ns as i64,
                                0,
                                "k {k} block {b:?} edge {edge}: vertex off the neighbour's grid"
                            );
                            assert_eq!(raw, hf.raw_at(sx, sz));
                        } else {
                            // On the neighbour's edge segment: linear between its vertices.
                            let a = along - along.rem_euclid(ns as i64);
                            let (ax, az, bx, bz) =
                                if edge % 2 == 0 { (a, sz, a + ns as i64, sz) } else { (sx, a, sx, a + ns as i64) };
                            let (ha, hb) = (hf.raw_at(ax, az), hf.raw_at(bx, bz));
                            let f = (along - a) as f32 / ns as f32;
                            assert!((raw - (ha + (hb - ha) * f)).abs() <= 1e-4 * (1.0 + ha.abs().max(hb.abs())));
                        }
                    }
                }
            }
        }
    }
    // A lone spike just past the centre: the flat half next to it stays at a coarse LOD
    // while the spike's blocks go down to LOD 0, so neighbours differ by many levels.
    let lone = field(257, 257, 1.0, |x, z| if (x, z) == (129, 129) { 50.0 } else { 0.0 });
    let lone_mm = MinMaxPyramid::build(&lone);
    let layout = BlockLayout::new(lone.n, 3).unwrap();
    let cam = Camera::look_at(Vec3::new(128.0, 300.0, 128.0), Vec3::new(128.0, 0.0, 127.0), 70.0, 640, 480, 0.05);
    let t = frame(&lone, &lone_mm, &layout, &cam, &cam, ErrorMode::Strict, 1.0);
    for b in &t.blocks {
        for (edge, &ns) in b.coarser.iter().enumerate() {
            if ns == 0 {
                continue;
            }
            seen.insert((ns / b.stride()).trailing_zeros());
            for t_ in 0..3 {
                let (u, v) = [(t_, 0), (2, t_), (t_, 2), (0, t_)][edge];
                let (sx, sz, raw) = block_vertex(&lone, &layout, b, u, v);
                // The flat side is at height 0 everywhere: every stitched vertex must be too,
                // unless it is the spike's own sample (a vertex of both blocks).
                if (sx, sz) != (129, 129) {
                    assert_eq!(raw, 0.0, "block {b:?} edge {edge} vertex ({u},{v}) at ({sx},{sz})");
                }
            }
        }
    }
    check_tiling(&lone, &lone_mm, &layout, &t.blocks, &cam).unwrap();
    let a = audit(&lone, &layout, &t, &cam);
    assert!(a.max_error_px <= 1.01, "lone spike: {}", a.max_error_px);
    // Differences of 1, 2 and more levels all occurred.
    assert!(seen.contains(&1) && seen.contains(&2) && seen.iter().any(|&d| d >= 3), "LOD differences seen: {seen:?}");
}

#[test]
fn full_lod_draws_every_visible_block_at_lod_0() {
    let hf = field(129, 129, 1.0, |x, z| (x + z) as f32 * 0.1);
    let mm = MinMaxPyramid::build(&hf);
    let layout = BlockLayout::new(hf.n, 17).unwrap();
    let cam = Camera::look_at(Vec3::new(64.0, 200.0, 64.0), Vec3::new(64.0, 0.0, 63.0), 60.0, 640, 480, 0.05);
    let t = traverse(&hf, &mm, &layout, &cam, LodSelect::Full);
    assert!(t.blocks.iter().all(|b| b.lod == 0));
    assert_eq!(t.blocks.len(), 64);
    check_tiling(&hf, &mm, &layout, &t.blocks, &cam).unwrap();
}
