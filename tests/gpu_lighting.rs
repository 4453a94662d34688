//! The lighting map (sun visibility, ambient occlusion) drawn by `glsl/lighting.frag`
//! against its CPU reference `vkterrain::draw::lighting`, on crafted fields built to make
//! shadows and occlusion extreme and on real data, under validation.

mod common;
use common::*;
use vkterrain::draw::lighting::{reference, source_reference, LightingSource, Sun, MAX_LIGHTING_SIDE};
use vkterrain::draw::lighting_gpu::{LightingMap, OwnLighting};
use vkterrain::gpu::terrain::TerrainGpu;
use vkterrain::input::load::{self, LoadOptions};
use vkterrain::lod::heightfield::Heightfield;
use vkterrain::lod::pyramid::MinMaxPyramid;

/// Differences between the GPU map (8-bit) and the reference: the largest, and the
/// share of texels off by more than 1.5/255 in either channel (on lavapipe: none).
fn compare(gpu: &[[u8; 2]], cpu: &[[f32; 2]]) -> (f32, f64) {
    assert_eq!(gpu.len(), cpu.len());
    let mut worst = 0.0f32;
    let mut off = 0usize;
    for (g, c) in gpu.iter().zip(cpu) {
        let d = (0..2).map(|i| (g[i] as f32 / 255.0 - c[i]).abs()).fold(0.0, f32::max);
        worst = worst.max(d);
        if d > 1.5 / 255.0 {
            off += 1;
        }
    }
    (worst, off as f64 / gpu.len() as f64)
}

fn check(device: &std::sync::Arc<vkterrain::vk::Device>, name: &str, hf: &Heightfield, suns: &[Sun], max_side: usize) {
    let mm = MinMaxPyramid::build(hf);
    let terrain = TerrainGpu::new(device, hf, &mm, None, None).unwrap();
    let mut map = LightingMap::with_max_side(device, hf, &terrain, None, max_side).unwrap();
    assert!(map.read().unwrap().iter().all(|&t| t == [255, 255]), "{name}: without a sun everything is lit");
    let mut previous: Option<Vec<[f32; 2]>> = None;
    for &sun in suns {
        map.set_sun(&LightingSource::whole(hf), Some(sun)).unwrap();
        let gpu = map.read().unwrap();
        let cpu = reference(hf, Some(sun), max_side);
        let (worst, share) = compare(&gpu, &cpu);
        println!("{name} {sun:?}: worst {worst:.4}, share off {share:.5}");
        // Only a texel whose march lands on a rounding boundary may differ by more than
        // 8-bit rounding.
        assert!(share <= 0.0005, "{name} {sun:?}: {share} of texels differ from the reference (worst {worst})");
        let shaded = cpu.iter().filter(|l| l[0] < 0.5).count();
        let occluded = cpu.iter().filter(|l| l[1] < 0.9).count();
        assert!(shaded > 0 && occluded > 0, "{name} {sun:?}: the field casts no shadow or occludes nothing");
        // The comparison can fail: the last sun's reference is far from this map.
        if let Some(p) = previous {
            let (_, share) = compare(&gpu, &p);
            assert!(share > 0.01, "{name}: maps for two suns should differ ({share})");
        }
        previous = Some(cpu);
    }
}

/// Every `stride`-th sample of `hf`: what a streamed terrain's coarser tiles hold.
fn every(hf: &Heightfield, stride: usize) -> Heightfield {
    let [w, h] = [hf.width, hf.height].map(|e| (e - 1) / stride + 1);
    let raw: Vec<f32> = (0..w * h).map(|i| hf.raw_at(((i % w) * stride) as i64, ((i / w) * stride) as i64)).collect();
    let spacing = [hf.spacing.x * stride as f32, hf.spacing.z * stride as f32];
    Heightfield::embed("every", w, h, &raw, hf.format, spacing, hf.height_scale).unwrap()
}

/// The map streamed frames make (`OwnLighting`: heights of its own, every `stride`-th
/// sample of `hf`) against its reference, which marches through `hf`'s samples and reads
/// the nearest one held.
fn check_strided(
    device: &std::sync::Arc<vkterrain::vk::Device>,
    name: &str,
    hf: &Heightfield,
    stride: usize,
    suns: &[Sun],
) {
    let mut own = OwnLighting::new(device, every(hf, stride), stride, [hf.width, hf.height], None, 0.0).unwrap();
    assert!(own.map.read().unwrap().iter().all(|&t| t == [255, 255]), "{name}: without a sun everything is lit");
    for &sun in suns {
        own.set_sun(Some(sun)).unwrap();
        let gpu = own.map.read().unwrap();
        let cpu = source_reference(&own.source(), Some(sun), MAX_LIGHTING_SIDE);
        let (worst, share) = compare(&gpu, &cpu);
        println!("{name} every {stride} {sun:?}: worst {worst:.4}, share off {share:.5}");
        assert!(share <= 0.0005, "{name} {sun:?}: {share} of texels differ from the reference (worst {worst})");
        assert!(cpu.iter().any(|l| l[0] < 0.5) && cpu.iter().any(|l| l[1] < 0.9), "{name} {sun:?}: nothing shaded");
    }
    // A taller terrain darkens the map: the height scale reaches the shader.
    let before = own.map.read().unwrap();
    own.set_height_scale(hf.height_scale * 3.0).unwrap();
    let (_, share) =
        compare(&own.map.read().unwrap(), &before.iter().map(|t| t.map(|v| v as f32 / 255.0)).collect::<Vec<_>>());
    assert!(share > 0.01, "{name}: a height scale three times larger changed {share} of the map");
}

#[test]
fn a_map_from_every_other_sample_matches_its_reference() {
    let device = gpu();
    let low_east = Sun { azimuth: 90.0, elevation: 12.0 };
    let odd = Sun { azimuth: 217.5, elevation: 33.0 };
    let bumps = field16(129, 129, 1.0, 0.01, |x, z| {
        (30000.0 + 9000.0 * ((x as f32 * 0.37).sin() + (z as f32 * 0.23).cos() * (x as f32 * 0.11).sin())) as u16
    });
    check_strided(&device, "bumps16", &bumps, 2, &[low_east, odd]);
    let ps = load::load(&data("puget_sound/ps_height_1k.png"), &LoadOptions::default()).unwrap();
    check_strided(&device, "puget sound", &ps, 4, &[Sun { azimuth: 260.0, elevation: 15.0 }]);
    finish(device);
}

#[test]
fn lighting_map_matches_the_reference() {
    let device = gpu();
    let low_east = Sun { azimuth: 90.0, elevation: 12.0 };
    let odd = Sun { azimuth: 217.5, elevation: 33.0 };
    // Walls of several heights along x and z, a pit and a spike: long shadows, deep
    // occlusion, shadow edges at every angle.
    let walls = field(97, 97, [2.0, 5.0], |x, z| {
        let (fx, fz) = (x as f32 - 48.0, z as f32 - 48.0);
        if x % 24 == 12 {
            (z % 7) as f32 * 3.0
        } else if z == 70 {
            20.0
        } else if fx * fx + fz * fz < 36.0 {
            -15.0
        } else if (x, z) == (80, 20) {
            60.0
        } else {
            0.0
        }
    });
    check(&device, "walls", &walls, &[low_east, odd, Sun::DEFAULT], MAX_LIGHTING_SIDE);
    // 16-bit heights (decoded in the shader), a rough sine field, a map with one texel
    // per two samples.
    let bumps = field16(129, 129, 1.0, 0.01, |x, z| {
        (30000.0 + 9000.0 * ((x as f32 * 0.37).sin() + (z as f32 * 0.23).cos() * (x as f32 * 0.11).sin())) as u16
    });
    check(&device, "bumps16", &bumps, &[low_east, odd], MAX_LIGHTING_SIDE);
    check(&device, "bumps16 halved", &bumps, &[odd, low_east], 65);
    // Real data: Puget Sound, the sun low in the west.
    let ps = load::load(&data("puget_sound/ps_height_1k.png"), &LoadOptions::default()).unwrap();
    check(&device, "puget sound", &ps, &[Sun { azimuth: 260.0, elevation: 15.0 }], MAX_LIGHTING_SIDE);
    finish(device);
}
