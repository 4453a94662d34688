//! Occlusion culling (SPEC section 10): a culled block, or part of a block, has no
//! visible sample. Over hundreds of low, horizon-level poses on real and crafted fields
//! (thin ridges, cliffs, a crater's rim), the frame drawn without the hidden blocks and
//! parts equals, pixel for pixel, the same selection drawn with nothing culled; mutations
//! that hide one visible block or part, or break the sweep's rule, make frames differ.
//! Runs under validation and fails on any message.

mod common;
use common::*;
use glam::Vec3;
use std::sync::Arc;
use vkterrain::draw::blocks::{BlocksRenderer, PixelPass, Shading, Target, COLOR_FORMAT};
use vkterrain::gpu::terrain::TerrainGpu;
use vkterrain::input::load::{self, LoadOptions};
use vkterrain::lod::block::{part_boxes, parts_outside, BlockLayout, DrawBlock, Traversal, PART_FRUSTUM_MARGIN_PX};
use vkterrain::lod::camera::Camera;
use vkterrain::lod::gie::{block_errors, group_errors_with, ErrorMode, ErrorParams, WorldPart};
use vkterrain::lod::heightfield::Heightfield;
use vkterrain::lod::occlusion::{self, Rule};
use vkterrain::lod::pyramid::MinMaxPyramid;
use vkterrain::lod::traversal::{traverse, BlockCaches, LodSelect};
use vkterrain::vk::Device;

/// A small deterministic generator (reproducible poses).
struct Rng(u64);
impl Rng {
    fn next(&mut self) -> f32 {
        self.0 = self.0.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
        ((self.0 >> 40) as f32) / ((1u64 << 24) as f32)
    }
}

struct Scene {
    device: Arc<Device>,
    hf: Heightfield,
    mm: MinMaxPyramid,
    layout: BlockLayout,
    terrain: Arc<TerrainGpu>,
    renderer: BlocksRenderer,
}

impl Scene {
    fn new(device: &Arc<Device>, hf: Heightfield, k: u32) -> Scene {
        let mm = MinMaxPyramid::build(&hf);
        let layout = BlockLayout::of(&hf, k).unwrap();
        let terrain = Arc::new(TerrainGpu::new(device, &hf, &mm, None, None).unwrap());
        let renderer = BlocksRenderer::new(device, &hf, &terrain, layout, COLOR_FORMAT, 1, None).unwrap();
        Scene { device: device.clone(), hf, mm, layout, terrain, renderer }
    }

    /// The renderer's selection for `cam` (strict, morphing, fresh CPU reference errors).
    fn select(&self, cam: &Camera, delta: f32) -> (Traversal, BlockCaches) {
        let p = ErrorParams::new(cam, ErrorMode::Strict);
        let errors = block_errors(&group_errors_with(&self.hf, &self.mm, &p, WorldPart::Exact), self.layout.m);
        let caches = BlockCaches::default();
        let select = LodSelect::errors(&errors, cam.position, delta, ErrorMode::Strict);
        (traverse(&self.hf, &self.mm, &caches, &self.layout, cam, select), caches)
    }

    fn render(&mut self, target: &Target, cam: &Camera, blocks: &[DrawBlock], pixels: PixelPass) -> Vec<u8> {
        let shading = Shading { pixels, ..Shading::default() };
        self.renderer.render_offscreen(&self.hf, &self.terrain, target, cam, blocks, &shading).unwrap().0
    }
}

/// Low poses looking along the ground: the camera a little above the terrain under it
/// (up to `above` world units), pitched from slightly up to 25 degrees down, over the
/// true extent (where culling applies).
fn low_poses(hf: &Heightfield, count: usize, above: f32, seed: u64) -> Vec<Camera> {
    let mut rng = Rng(seed);
    let (wx, wz) = hf.world_extent();
    (0..count)
        .map(|_| {
            let (x, z) = (wx * (0.05 + 0.9 * rng.next()), wz * (0.05 + 0.9 * rng.next()));
            let y = hf.surface_height(x, z) + hf.spacing.min() + above * rng.next();
            let yaw = rng.next() * std::f32::consts::TAU;
            let pitch = 0.05 - 0.5 * rng.next();
            let dir = Vec3::new(yaw.cos() * pitch.cos(), pitch.sin(), yaw.sin() * pitch.cos());
            let pos = Vec3::new(x, y, z);
            Camera::look_at(pos, pos + dir, 30.0 + 40.0 * rng.next(), 240, 144, hf.spacing.min() * 0.05)
        })
        .collect()
}

/// What a pose set found.
#[derive(Default, Debug)]
struct Tally {
    poses: usize,
    culled_poses: usize,
    blocks: usize,
    /// Blocks hidden whole.
    hidden: usize,
    parts: usize,
    /// Parts hidden, those of blocks hidden whole included.
    hidden_parts: usize,
    /// Poses whose culled frame differs from the unculled one, with the pixels differing.
    differing: Vec<(usize, usize)>,
}

/// Per pose: the selection, the parts `hide` says are hidden (per block, as
/// `DrawBlock::hidden_parts`); the frame without them against the frame with every
/// selected block whole.
fn check(
    scene: &mut Scene,
    poses: &[Camera],
    delta: f32,
    pixels: PixelPass,
    mut hide: impl FnMut(&Scene, &Camera, &Traversal, &BlockCaches) -> Option<Vec<u16>>,
) -> Tally {
    let mut tally = Tally::default();
    let target = Target::new(&scene.device, poses[0].width, poses[0].height).unwrap();
    let all = scene.layout.all_parts();
    for (i, cam) in poses.iter().enumerate() {
        let (t, caches) = scene.select(cam, delta);
        tally.poses += 1;
        tally.blocks += t.blocks.len();
        tally.parts += t.blocks.len() * all.count_ones() as usize;
        let Some(hidden) = hide(scene, cam, &t, &caches) else { continue };
        assert_eq!(hidden.len(), t.blocks.len(), "one mask per block");
        tally.culled_poses += 1;
        tally.hidden += hidden.iter().filter(|&&h| h == all).count();
        let parts: usize = hidden.iter().map(|h| h.count_ones() as usize).sum();
        tally.hidden_parts += parts;
        if parts == 0 {
            continue;
        }
        assert!(t.blocks.iter().all(|b| b.hidden_parts == 0), "the traversal hides nothing itself");
        let kept: Vec<DrawBlock> = (t.blocks.iter().zip(&hidden))
            .filter(|(_, &h)| h != all)
            .map(|(b, &h)| DrawBlock { hidden_parts: h, ..*b })
            .collect();
        let all = scene.render(&target, cam, &t.blocks, pixels);
        let culled = scene.render(&target, cam, &kept, pixels);
        assert_eq!(all.len(), culled.len());
        let diff = all.chunks(4).zip(culled.chunks(4)).filter(|(a, b)| a != b).count();
        if diff > 0 {
            tally.differing.push((i, diff));
        }
    }
    tally
}

fn sound(scene: &Scene, cam: &Camera, t: &Traversal, caches: &BlockCaches) -> Option<Vec<u16>> {
    occlusion::hidden_parts(&scene.hf, &scene.mm, caches, &scene.layout, cam, t).ok()
}

fn with_rule(rule: Rule) -> impl FnMut(&Scene, &Camera, &Traversal, &BlockCaches) -> Option<Vec<u16>> {
    move |scene, cam, t, caches| {
        occlusion::hidden_parts_with(&scene.hf, &scene.mm, caches, &scene.layout, cam, t, rule).ok()
    }
}

/// Puget Sound's 1k map, a 513 x 513 crop at its own scale.
fn puget_crop() -> Heightfield {
    let hf = load::load(&data("puget_sound/ps_height_1k.png"), &LoadOptions::default()).unwrap();
    let (hs, sp) = (hf.height_scale, hf.spacing);
    let mut crop = field(513, 513, sp, |x, z| hf.raw_at(x as i64 + 300, z as i64 + 200) * hs);
    crop.source = "Puget Sound 1k, 513 x 513 crop".into();
    crop
}

/// Thin walls one sample wide, 40 units tall, every 24 samples across x, over gentle
/// noise: each hides a strip behind it, and blocks that hold a wall have a low minimum.
fn thin_ridges() -> Heightfield {
    let mut hf = field(257, 257, 1.0, |x, z| {
        let noise = (((x * 7919) ^ (z * 104729)).wrapping_mul(2654435761) % 17) as f32 * 0.05;
        if x % 24 == 12 {
            40.0 + noise
        } else {
            noise
        }
    });
    hf.source = "thin ridges".into();
    hf
}

/// A cliff: a plateau 60 units up for x < 128, a plain beyond, a sheer step between.
fn cliff() -> Heightfield {
    let mut hf = field(257, 257, 2.0, |x, z| {
        let wobble = ((z as f32) * 0.3).sin() * 0.5;
        if x < 128 {
            60.0 + wobble
        } else {
            wobble
        }
    });
    hf.source = "cliff".into();
    hf
}

/// The cliff with pillars one sample wide and 80 units tall every 9 samples over the
/// plain: seen from the plateau the plain is hidden behind the edge, but the pillars'
/// tops show over it, so a part that holds one is visible though most of it is not.
fn cliff_pillars() -> Heightfield {
    let mut hf = field(257, 257, 2.0, |x, z| {
        let wobble = ((z as f32) * 0.3).sin() * 0.5;
        if x < 128 {
            60.0 + wobble
        } else if x % 9 == 4 && z % 9 == 4 {
            80.0
        } else {
            wobble
        }
    });
    hf.source = "cliff with pillars".into();
    hf
}

/// A crater: a steep rim 50 units high round a bowl, seen from outside and inside.
fn crater() -> Heightfield {
    let mut hf = field(257, 257, 1.0, |x, z| {
        let r = ((x as f32 - 128.0).powi(2) + (z as f32 - 128.0).powi(2)).sqrt();
        let rim = (-(r - 70.0).powi(2) / 30.0).exp() * 50.0;
        if r < 70.0 {
            rim - 10.0 * (1.0 - r / 70.0)
        } else {
            rim
        }
    });
    hf.source = "crater".into();
    hf
}

#[test]
fn culled_frames_equal_unculled_frames() {
    let device = gpu();
    let mut report = Vec::new();
    let cases: [(Heightfield, u32, usize, f32); 5] = [
        (puget_crop(), 17, 70, 300.0),
        (thin_ridges(), 17, 60, 30.0),
        (cliff(), 17, 60, 80.0),
        (cliff_pillars(), 17, 40, 40.0),
        (crater(), 17, 60, 40.0),
    ];
    let (mut poses_all, mut culled_all) = (0, 0);
    let mut crater_share = 0.0;
    let mut partial_parts = 0;
    for (n, (hf, k, count, above)) in cases.into_iter().enumerate() {
        let source = hf.source.clone();
        let mut scene = Scene::new(&device, hf, k);
        let poses = low_poses(&scene.hf, count, above, 17 + n as u64);
        for (delta, pixels) in [(1.0f32, PixelPass::Deferred), (4.0, PixelPass::Forward)] {
            let take = if pixels == PixelPass::Deferred { poses.len() } else { poses.len() / 3 };
            let t = check(&mut scene, &poses[..take], delta, pixels, sound);
            assert!(
                t.differing.is_empty(),
                "{source}, delta {delta}, {pixels:?}: culled frames differ from unculled ones (pose, pixels): {:?}",
                t.differing
            );
            report.push(format!(
                "{source} (spacing {:?}) delta {delta} {pixels:?}: {} poses, {} culled, {} of {} blocks and {} of {} parts hidden",
                scene.hf.spacing, t.poses, t.culled_poses, t.hidden, t.blocks, t.hidden_parts, t.parts
            ));
            poses_all += t.poses;
            culled_all += t.culled_poses;
            if source == "crater" && delta == 1.0 {
                crater_share = t.hidden as f64 / t.blocks as f64;
            }
            if delta == 1.0 {
                // Parts hidden beyond whole blocks: the parts' own tests at work.
                partial_parts += t.hidden_parts - t.hidden * scene.layout.all_parts().count_ones() as usize;
            }
        }
    }
    println!("occlusion: {}", report.join("; "));
    // Not vacuous: culling ran on most poses, and where a rim hides the far side (the
    // crater, seen from outside and in) it hid a real share of the blocks.
    assert!(poses_all >= 250, "{poses_all} poses");
    assert!(culled_all * 10 >= poses_all * 8, "culling ran on only {culled_all} of {poses_all} poses");
    assert!(crater_share >= 0.25, "only {:.1} % of the crater's blocks hidden", crater_share * 100.0);
    assert!(partial_parts >= 100, "only {partial_parts} parts of partly visible blocks hidden");
    finish(device);
}

/// The check catches what it must: hiding one visible block (the nearest drawn block
/// ahead of the camera), occluders placed at their blocks' tops, and blocks tested
/// against occluders that are not wholly nearer than they are (no sweep order).
#[test]
fn culling_mutations_change_frames() {
    let device = gpu();
    let mut scene = Scene::new(&device, crater(), 17);
    let poses = low_poses(&scene.hf, 40, 40.0, 5);
    // The block under a point just ahead of the camera (visible on almost every pose).
    let one_visible = |scene: &Scene, cam: &Camera, t: &Traversal, caches: &BlockCaches| {
        let mut hidden = sound(scene, cam, t, caches)?;
        let ahead = cam.position + cam.forward * 5.0;
        let centre = t.blocks.iter().position(|b| {
            let s = scene.layout.block_samples(b.lod) as f32;
            let (ox, oz) = (b.bx as f32 * s, b.bz as f32 * s);
            (ox..=ox + s).contains(&(ahead.x / scene.hf.spacing.x))
                && (oz..=oz + s).contains(&(ahead.z / scene.hf.spacing.z))
        })?;
        if hidden[centre] == scene.layout.all_parts() {
            return None;
        }
        hidden[centre] = scene.layout.all_parts();
        Some(hidden)
    };
    // Only the part of that block under the point ahead.
    let one_visible_part = |scene: &Scene, cam: &Camera, t: &Traversal, caches: &BlockCaches| {
        let mut hidden = sound(scene, cam, t, caches)?;
        let ahead = cam.position + cam.forward * 5.0;
        let (x, z) = (ahead.x / scene.hf.spacing.x, ahead.z / scene.hf.spacing.z);
        let p = scene.layout.parts_per_side();
        let (i, bit) = t.blocks.iter().enumerate().find_map(|(i, b)| {
            let s = scene.layout.block_samples(b.lod) as f32;
            let (ox, oz) = (b.bx as f32 * s, b.bz as f32 * s);
            let inside = (ox..ox + s).contains(&x) && (oz..oz + s).contains(&z);
            let (px, pz) = (((x - ox) / s * p as f32) as u32, ((z - oz) / s * p as f32) as u32);
            inside.then(|| (i, 1u16 << (pz * p + px)))
        })?;
        if hidden[i] & bit != 0 {
            return None;
        }
        hidden[i] |= bit;
        Some(hidden)
    };
    let mut mutations: Vec<(&str, Tally)> = vec![
        ("one visible block hidden", check(&mut scene, &poses, 1.0, PixelPass::Deferred, one_visible)),
        ("one visible part hidden", check(&mut scene, &poses, 1.0, PixelPass::Deferred, one_visible_part)),
        ("occluders at their top", check(&mut scene, &poses, 1.0, PixelPass::Deferred, with_rule(Rule::OccluderTop))),
        ("no sweep order", check(&mut scene, &poses, 1.0, PixelPass::Deferred, with_rule(Rule::Unordered))),
    ];
    drop(scene);
    // A part tested at its lowest sample hides a pillar whose top shows over the cliff's
    // edge (on the crater's smooth slopes a part's lowest and highest samples are too
    // close to tell).
    let mut scene = Scene::new(&device, cliff_pillars(), 17);
    let poses = low_poses(&scene.hf, 40, 40.0, 5);
    let t = check(&mut scene, &poses, 1.0, PixelPass::Deferred, with_rule(Rule::PartBottom));
    mutations.push(("parts at their lowest", t));
    for (what, t) in &mutations {
        println!("mutation {what}: {} of {} poses differ", t.differing.len(), t.culled_poses);
        assert!(!t.differing.is_empty(), "mutation '{what}' went unnoticed over {} poses", t.poses);
    }
    drop(scene);
    finish(device);
}

/// The parts of drawn blocks that lie outside the frustum (widened by
/// `PART_FRUSTUM_MARGIN_PX`), as the draw thread leaves them out.
fn outside(margin_px: f32) -> impl FnMut(&Scene, &Camera, &Traversal, &BlockCaches) -> Option<Vec<u16>> {
    move |scene, cam, t, _| {
        let frustum = cam.frustum_widened(margin_px);
        Some(t.blocks.iter().map(|b| parts_outside(&scene.hf, &scene.mm, &scene.layout, &frustum, b)).collect())
    }
}

/// Frustum culling of parts (the blocks stay, their parts outside the image go): over
/// low poses on a real and two crafted fields, where a block crosses the image's edge
/// on nearly every pose, the frame without those parts equals the frame with every
/// block whole. Mutations: parts culled by a frustum narrower than the image, parts
/// tested at their lowest height (a peak that rises into the image from below its
/// bottom edge). (That a part's box holds its stitched triangles is the unit test
/// `part_boxes_hold_their_triangles`: a neighbour 3 LODs coarser at the image's edge is
/// too rare in a frame to catch the mutation there.)
#[test]
fn parts_outside_the_frustum_are_never_seen() {
    let device = gpu();
    let mut report = Vec::new();
    let cases: [(Heightfield, usize, f32); 3] =
        [(puget_crop(), 60, 300.0), (cliff_pillars(), 50, 40.0), (thin_ridges(), 50, 30.0)];
    let mut hidden_all = 0;
    let mut mutations: Vec<(String, Tally)> = Vec::new();
    for (n, (hf, count, above)) in cases.into_iter().enumerate() {
        let source = hf.source.clone();
        let mut scene = Scene::new(&device, hf, 17);
        let poses = low_poses(&scene.hf, count, above, 31 + n as u64);
        let t = check(&mut scene, &poses, 1.0, PixelPass::Deferred, outside(PART_FRUSTUM_MARGIN_PX));
        assert!(
            t.differing.is_empty(),
            "{source}: frames without the parts outside differ (pose, pixels): {:?}",
            t.differing
        );
        report.push(format!("{source}: {} poses, {} of {} parts outside", t.poses, t.hidden_parts, t.parts));
        hidden_all += t.hidden_parts;
        if source == "cliff with pillars" {
            let narrow = check(&mut scene, &poses, 1.0, PixelPass::Deferred, outside(-2.0));
            mutations.push((format!("{source}: frustum 2 px inside the image"), narrow));
            let lowest = |scene: &Scene, cam: &Camera, t: &Traversal, _: &BlockCaches| {
                let frustum = cam.frustum_widened(PART_FRUSTUM_MARGIN_PX);
                let hs = scene.hf.height_scale;
                let masks = t.blocks.iter().map(|b| {
                    part_boxes(&scene.mm, &scene.layout, b)
                        .filter(|pb| {
                            let (x1, z1) = (pb.x0 + pb.size, pb.z0 + pb.size);
                            let (min, max) = scene.hf.world_box(pb.x0, pb.z0, x1, z1, [pb.raw[0] * hs; 2]);
                            !frustum.intersects_aabb(min, max)
                        })
                        .fold(0, |m, pb| m | pb.bit)
                });
                Some(masks.collect())
            };
            mutations.push((
                format!("{source}: parts at their lowest"),
                check(&mut scene, &poses, 1.0, PixelPass::Deferred, lowest),
            ));
        }
    }
    println!("parts outside the frustum: {}", report.join("; "));
    assert!(hidden_all >= 500, "only {hidden_all} parts outside the frustum: the check is nearly vacuous");
    for (what, t) in &mutations {
        println!("mutation {what}: {} of {} poses differ", t.differing.len(), t.poses);
        assert!(!t.differing.is_empty(), "mutation '{what}' went unnoticed over {} poses", t.poses);
    }
    finish(device);
}
