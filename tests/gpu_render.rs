//! GPU rendering checks (SPEC section 7): crafted scenes with known pixels, no cracks
//! over many poses and deltas, and fidelity against the full-resolution render. Every
//! test runs under validation and fails on any message.

mod common;
use common::*;
use glam::Vec3;
use std::sync::Arc;
use vkterrain::app::bench::image_difference;
use vkterrain::draw::blocks::{BlocksRenderer, DrawStats, NormalSource, PixelPass, Shading, Target, COLOR_FORMAT};
use vkterrain::draw::lighting::Sun;
use vkterrain::draw::raycast::Raycast;
use vkterrain::errors::activity::ErrorsActivity;
use vkterrain::gpu::terrain::{TerrainGpu, Texture};
use vkterrain::input::load::{self, LoadOptions};
use vkterrain::lod::block::BlockLayout;
use vkterrain::lod::camera::Camera;
use vkterrain::lod::gie::{ErrorMode, ErrorParams};
use vkterrain::lod::heightfield::Heightfield;
use vkterrain::lod::pyramid::MinMaxPyramid;
use vkterrain::lod::traversal::{traverse, BlockCaches, LodSelect};
use vkterrain::vk::Device;

const MAGENTA: [u8; 3] = [255, 0, 255];

struct Scene {
    device: Arc<Device>,
    hf: Arc<Heightfield>,
    mm: MinMaxPyramid,
    layout: BlockLayout,
    terrain: Arc<TerrainGpu>,
    renderer: BlocksRenderer,
    /// Geomorphing in error-driven renders (on, as the renderer's default).
    morph: bool,
}

impl Scene {
    /// A scene lit by `sun` (`None`: no shadows or occlusion, for tests of geometry).
    fn new(device: &Arc<Device>, hf: Heightfield, k: u32, sun: Option<Sun>) -> Scene {
        let mm = MinMaxPyramid::build(&hf);
        let layout = BlockLayout::of(&hf, k).unwrap();
        let terrain = Arc::new(TerrainGpu::new(device, &hf, &mm, None, None).unwrap());
        let renderer = BlocksRenderer::new(device, &hf, &terrain, layout, COLOR_FORMAT, 1, sun).unwrap();
        Scene { device: device.clone(), hf: Arc::new(hf), mm, layout, terrain, renderer, morph: true }
    }

    /// Renders with `--lod full` (errors = None) or the paper's method at `delta`.
    fn render(&mut self, cam: &Camera, errors: Option<(&ErrorsActivity, f32)>, shading: &Shading) -> Vec<u8> {
        self.render_mode(cam, errors, ErrorMode::Strict, shading)
    }

    fn render_mode(
        &mut self,
        cam: &Camera,
        errors: Option<(&ErrorsActivity, f32)>,
        mode: ErrorMode,
        shading: &Shading,
    ) -> Vec<u8> {
        let gen;
        let select = match errors {
            None => LodSelect::Full,
            Some((activity, delta)) => {
                gen = activity.wait_for(ErrorParams::new(cam, mode), std::time::Duration::from_secs(120)).unwrap();
                LodSelect::errors(&gen.errors, gen.params.camera, delta, gen.params.mode).with_morph(self.morph)
            }
        };
        self.render_select(cam, select, shading).0
    }

    /// Renders the blocks `select` chooses, with the frame's stats.
    fn render_select(&mut self, cam: &Camera, select: LodSelect, shading: &Shading) -> (Vec<u8>, DrawStats) {
        let target = Target::new(&self.device, cam.width, cam.height).unwrap();
        let t = traverse(&self.hf, &self.mm, &BlockCaches::default(), &self.layout, cam, select);
        self.renderer.render_offscreen(&self.hf, &self.terrain, &target, cam, &t.blocks, shading).unwrap()
    }
}

fn plain() -> Shading {
    Shading { sky: false, background: [1.0, 0.0, 1.0], ..Shading::default() }
}

fn pixel(px: &[u8], w: u32, x: u32, y: u32) -> [u8; 3] {
    let i = ((y * w + x) * 4) as usize;
    [px[i], px[i + 1], px[i + 2]]
}

#[test]
fn flat_plane_covers_exactly_its_projection() {
    let device = gpu();
    let mut scene = Scene::new(&device, field(33, 33, 1.0, |_, _| 0.0), 9, None);
    let cam = Camera::look_at(Vec3::new(16.0, 20.0, 40.0), Vec3::new(16.0, 0.0, 16.0), 60.0, 160, 120, 0.05);
    let px = scene.render(&cam, None, &plain());
    let vp = cam.view_proj();
    // The projected quad of the plane's corners.
    let corners: Vec<(f32, f32)> = [(0.0, 0.0), (32.0, 0.0), (32.0, 32.0), (0.0, 32.0)]
        .iter()
        .map(|&(x, z)| cam.project(&vp, Vec3::new(x, 0.0, z)).unwrap())
        .collect();
    // Winding of the projected quad, so that the distance is positive inside.
    let area: f32 = (0..4).map(|i| corners[i].0 * corners[(i + 1) % 4].1 - corners[(i + 1) % 4].0 * corners[i].1).sum();
    let winding = area.signum();
    let inside = |x: f32, y: f32| -> f32 {
        // Signed distance to the convex quad (positive inside), in pixels.
        let mut d = f32::INFINITY;
        for i in 0..4 {
            let (ax, ay) = corners[i];
            let (bx, by) = corners[(i + 1) % 4];
            let (ex, ey) = (bx - ax, by - ay);
            let len = (ex * ex + ey * ey).sqrt();
            d = d.min(-winding * ((x - ax) * ey - (y - ay) * ex) / len);
        }
        d
    };
    assert!(inside(80.0, 80.0) > 0.0, "the plane is in view");
    let mut terrain_colour = None;
    let (mut n_in, mut n_out) = (0, 0);
    for y in 0..cam.height {
        for x in 0..cam.width {
            let d = inside(x as f32 + 0.5, y as f32 + 0.5);
            let c = pixel(&px, cam.width, x, y);
            if d > 1.5 {
                n_in += 1;
                assert_ne!(c, MAGENTA, "pixel ({x},{y}) inside the plane shows background");
                // A flat plane under a directional light has one colour.
                assert_eq!(*terrain_colour.get_or_insert(c), c, "pixel ({x},{y})");
            } else if d < -1.5 {
                n_out += 1;
                assert_eq!(c, MAGENTA, "pixel ({x},{y}) outside the plane is not background");
            }
        }
    }
    assert!(n_in > 1000 && n_out > 1000, "{n_in} inside, {n_out} outside");
    drop(scene);
    finish(device);
}

/// A camera close over the ground sees ground in every pixel: on a summit at eye height
/// (2 m) looking down ahead, and half a metre over a 3000 m cliff's slope looking at the
/// wall (0.027 m away along its normal): the near plane (`lod::view::near_plane`) is under
/// both. At a twentieth of the spacing (8 m here, as on Puget Sound 1k) the first view
/// showed nothing; at a 500th (0.32 m) the second did not.
#[test]
fn a_camera_close_over_the_ground_sees_it_at_its_feet() {
    let device = gpu();
    let dome = field(65, 65, 160.0, |x, z| {
        let (dx, dz) = (x as f32 - 32.0, z as f32 - 32.0);
        3000.0 - 2.0 * (dx * dx + dz * dz)
    });
    let cliff = field(65, 65, 160.0, |x, _| if x > 32 { 3000.0 } else { 0.0 });
    let summit = Vec3::new(32.0 * 160.0, 3002.0, 32.0 * 160.0);
    // Over the middle of the slope between columns 32 and 33, half a metre above it.
    let slope = Vec3::new(32.5 * 160.0, 1500.5, 20.0 * 160.0);
    for (name, hf, eye, look) in [
        ("summit", dome, summit, summit + Vec3::new(0.0, -1.0, 0.3)),
        ("cliff", cliff, slope, slope + Vec3::new(1.0, 0.0, 0.0)),
    ] {
        let near = vkterrain::lod::view::near_plane(&hf);
        let cam = Camera::look_at(eye, look, 60.0, 160, 120, near);
        let mut scene = Scene::new(&device, hf, 17, None);
        let activity = ErrorsActivity::start(&device, scene.terrain.clone(), scene.hf.clone(), scene.layout).unwrap();
        for errors in [None, Some((&activity, 1.0))] {
            let px = scene.render(&cam, errors, &plain());
            let holes = (0..cam.height)
                .flat_map(|y| (0..cam.width).map(move |x| (x, y)))
                .filter(|&(x, y)| pixel(&px, cam.width, x, y) == MAGENTA)
                .count();
            assert_eq!(holes, 0, "{name}: {holes} of 19200 pixels show no ground (near plane {near} m)");
        }
        activity.stop().unwrap();
    }
    finish(device);
}

#[test]
fn spike_appears_where_the_camera_projects_it() {
    let device = gpu();
    let flat = field(65, 65, 1.0, |_, _| 0.0);
    // A spike with a flat 3 x 3 top (a thin tip may fall between pixel centres).
    let spiky = field(65, 65, 1.0, |x, z| if (39..=41).contains(&x) && (23..=25).contains(&z) { 12.0 } else { 0.0 });
    let cam = Camera::look_at(Vec3::new(20.0, 45.0, 70.0), Vec3::new(32.0, 0.0, 30.0), 60.0, 200, 150, 0.05);
    let a = Scene::new(&device, flat, 17, None).render(&cam, None, &plain());
    let b = Scene::new(&device, spiky, 17, None).render(&cam, None, &plain());
    let vp = cam.view_proj();
    let (tx, ty) = cam.project(&vp, Vec3::new(40.0, 12.0, 24.0)).unwrap();
    // Every changed pixel lies inside the projection of the spike's pyramid and the
    // samples whose shading it changes (normals use central differences blended over a
    // cell, so up to two samples away), and the apex pixel is among them.
    let mut pts = vec![(tx, ty)];
    for dz in -3..=3 {
        for dx in -3..=3 {
            pts.push(cam.project(&vp, Vec3::new(40.0 + dx as f32, 0.0, 24.0 + dz as f32)).unwrap());
        }
    }
    let (x0, x1) = pts.iter().fold((f32::MAX, f32::MIN), |(lo, hi), p| (lo.min(p.0), hi.max(p.0)));
    let (y0, y1) = pts.iter().fold((f32::MAX, f32::MIN), |(lo, hi), p| (lo.min(p.1), hi.max(p.1)));
    let mut changed = 0;
    let mut top: Option<(u32, u32)> = None;
    for y in 0..cam.height {
        for x in 0..cam.width {
            if pixel(&a, cam.width, x, y) != pixel(&b, cam.width, x, y) {
                changed += 1;
                top.get_or_insert((x, y));
                let (fx, fy) = (x as f32 + 0.5, y as f32 + 0.5);
                assert!(
                    fx >= x0 - 1.5 && fx <= x1 + 1.5 && fy >= y0 - 1.5 && fy <= y1 + 1.5,
                    "pixel ({x},{y}) changed outside the spike's footprint"
                );
            }
        }
    }
    assert!(changed > 20, "the spike changed only {changed} pixels");
    // The centre of the spike's top face shows the spike, and nothing above its top edge
    // changed.
    let (ax, ay) = (tx as u32, ty as u32);
    assert_ne!(
        pixel(&a, cam.width, ax, ay),
        pixel(&b, cam.width, ax, ay),
        "the top of the spike ({ax},{ay}) did not change"
    );
    let far_edge = cam.project(&vp, Vec3::new(40.0, 12.0, 23.0)).unwrap().1;
    assert!(top.unwrap().1 as f32 + 0.5 >= far_edge - 1.5, "changed pixel above the spike's top edge");
    finish(device);
}

/// The terrain shader reads the lighting map where it should: a wall running north-south
/// with the sun low in the east shades a band west of it and leaves the ground east of
/// it lit. A map read transposed would shade an east-west band instead, and a sun
/// direction with the wrong sign the east side; both fail here.
#[test]
fn shadows_fall_away_from_the_sun() {
    let device = gpu();
    let wall = field(65, 65, 1.0, |x, _| if x == 40 { 10.0 } else { 0.0 });
    let east = Sun { azimuth: 90.0, elevation: 30.0 };
    let mut scene = Scene::new(&device, wall, 17, Some(east));
    let cam = Camera::look_at(Vec3::new(32.0, 90.0, 75.0), Vec3::new(32.0, 0.0, 30.0), 60.0, 320, 240, 0.05);
    let img = scene.render(&cam, None, &plain());
    let vp = cam.view_proj();
    let brightness = |x: f32, z: f32| {
        let (px, py) = cam.project(&vp, Vec3::new(x, 0.0, z)).unwrap();
        assert!(px >= 0.0 && py >= 0.0 && px < 320.0 && py < 240.0, "({x}, {z}) is off screen");
        pixel(&img, cam.width, px as u32, py as u32).iter().map(|&c| c as f32).sum::<f32>()
    };
    // The shadow is 10 / tan 30 = 17.3 samples long: x from 23 to 40 is in it. In the
    // shadow only the ambient term is left: about 0.6 of the lit brightness in sRGB.
    for z in [12.0, 30.0, 48.0] {
        let (shaded, lit) = (brightness(32.0, z), brightness(48.0, z));
        println!("z {z}: west of the wall {shaded}, east {lit}");
        assert!(shaded < 0.75 * lit, "z {z}: west of the wall {shaded} is not darker than east {lit}");
        // Beyond the shadow's end the west side is lit again.
        let beyond = brightness(12.0, z);
        assert!(beyond > 0.85 * lit, "z {z}: beyond the shadow {beyond}, east {lit}");
    }
    drop(scene);
    finish(device);
}

/// Cameras 10 to 40 km above the middle of the terrain looking down at 65 to 88 degrees (oblique, so a
/// crack's vertical slit would show), whose whole view is terrain.
fn downward_poses(hf: &Heightfield, count: usize) -> Vec<Camera> {
    let (wx, wz) = hf.world_extent();
    (0..count)
        .map(|i| {
            let f = (i as f32 + 0.5) / count as f32;
            let x = wx * (0.35 + 0.3 * f);
            let z = wz * (0.35 + 0.3 * ((f * 7.3).fract()));
            let ground = hf.surface_height(x, z);
            // High enough that the view spans many blocks of different LODs.
            let alt = hf.spacing.min() * (60.0 + 190.0 * ((f * 3.7).fract()));
            let pos = Vec3::new(x, ground + alt, z);
            let pitch = (65.0f32 + 23.0 * ((f * 5.1).fract())).to_radians();
            let yaw = f * std::f32::consts::TAU * 3.0;
            let dir = Vec3::new(yaw.cos() * pitch.cos(), -pitch.sin(), yaw.sin() * pitch.cos());
            Camera::look_at(pos, pos + dir, 50.0, 200, 150, hf.spacing.min() * 0.05)
        })
        .collect()
}

#[test]
fn no_cracks_when_the_whole_frame_is_terrain() {
    let device = gpu();
    let hf = load::load(&data("puget_sound/ps_height_1k.png"), &LoadOptions::default()).unwrap();
    let mut frames = 0;
    // Small blocks put many LOD boundaries in view.
    for k in [9, 33] {
        let mut scene = Scene::new(&device, hf.clone(), k, None);
        let activity = ErrorsActivity::start(&device, scene.terrain.clone(), scene.hf.clone(), scene.layout).unwrap();
        let poses = downward_poses(&scene.hf, 12);
        for cam in &poses {
            // Large deltas put very coarse blocks next to fine ones, where an unstitched
            // T-junction opens gaps many pixels tall (this test fails with stitching off).
            for (delta, mode) in [
                (1.0f32, ErrorMode::Strict),
                (8.0, ErrorMode::Strict),
                (64.0, ErrorMode::Strict),
                (16.0, ErrorMode::Paper),
            ] {
                let px = scene.render_mode(cam, Some((&activity, delta)), mode, &plain());
                let bad = px.chunks(4).filter(|p| p[..3] == MAGENTA).count();
                assert_eq!(
                    bad, 0,
                    "{bad} background pixels at camera {:?}, delta {delta}, {mode:?} mode",
                    cam.position
                );
                frames += 1;
            }
        }
        activity.stop().unwrap();
    }
    assert_eq!(frames, 96);
    finish(device);
}

#[test]
fn fidelity_against_the_full_resolution_render() {
    let device = gpu();
    let hf = load::load(&data("puget_sound/ps_height_1k.png"), &LoadOptions::default()).unwrap();
    let mut scene = Scene::new(&device, hf, 33, Some(Sun::DEFAULT));
    let activity = ErrorsActivity::start(&device, scene.terrain.clone(), scene.hf.clone(), scene.layout).unwrap();
    let (wx, wz) = scene.hf.world_extent();
    let views = [
        // The paper's start: from above one edge, the whole terrain visible.
        Camera::look_at(
            Vec3::new(wx * 0.5, 45_000.0, wz + 30_000.0),
            Vec3::new(wx * 0.5, 0.0, wz * 0.45),
            60.0,
            640,
            480,
            8.0,
        ),
        // Low over the mountains towards Rainier.
        Camera::look_at(
            Vec3::new(wx * 0.55, 3_000.0, wz * 0.5),
            Vec3::new(wx * 0.8, 1_500.0, wz * 0.85),
            60.0,
            640,
            480,
            8.0,
        ),
    ];
    for (cam, morph) in views.iter().flat_map(|c| [(c, true), (c, false)]) {
        scene.morph = morph;
        let full = scene.render(cam, None, &Shading::default());
        for delta in [0.5f32, 1.0, 2.0, 5.0] {
            let lod = scene.render(cam, Some((&activity, delta)), &Shading::default());
            let (rmse, share) = image_difference(&full, &lod);
            println!(
                "camera {:?} delta {delta} morph {morph}: RMSE {rmse:.3}, {:.3}% of pixels off by > 16",
                cam.position,
                share * 100.0
            );
            // A bound of delta pixels moves silhouettes by at most delta pixels and leaves
            // shading (normals come from the heightfield) unchanged, so differences stay
            // on a thin band of edges. ATLOD reports RMSE 2.78 for GeoMipMapping: at
            // delta <= 1 we must stay below it. (The first wave held RMSE < 1.5 here with a
            // loose bound that left part of delta unused; the exact bound spends more of
            // it on fewer triangles, and geomorphing more: measured at the start view RMSE
            // 1.94 at delta 1 with morphing, 1.66 without, with water blended from the
            // samples' sea flags and the default sun's shadows.)
            if delta <= 1.0 {
                assert!(rmse < 2.78, "delta {delta}: RMSE {rmse}");
                assert!(share < 0.005, "delta {delta}: {share}");
            }
            assert!(rmse < 2.78 * delta.max(1.0) as f64, "delta {delta}: RMSE {rmse}");
        }
    }
    activity.stop().unwrap();
    drop(scene);
    finish(device);
}

/// Two 320 x 240 views of `hf` for the shading comparisons: the whole field from beyond
/// its south edge, and obliquely across it from above its north-west quarter.
fn shading_views(hf: &Heightfield) -> [Camera; 2] {
    let (wx, wz) = hf.world_extent();
    let top = hf.raw.iter().cloned().fold(f32::MIN, f32::max) * hf.height_scale;
    [
        Camera::look_at(
            Vec3::new(wx * 0.5, top + wx * 0.3, wz * 1.2),
            Vec3::new(wx * 0.5, 0.0, wz * 0.4),
            60.0,
            320,
            240,
            1.0,
        ),
        Camera::look_at(
            Vec3::new(wx * 0.2, top * 1.1 + 5.0, wz * 0.3),
            Vec3::new(wx * 0.8, 0.0, wz * 0.7),
            60.0,
            320,
            240,
            0.1,
        ),
    ]
}

/// The gradient map (four fetches per pixel) shades like the first wave's sixteen
/// height fetches: the full-resolution reference image does not change beyond 8-bit
/// rounding, with the sky drawn last behind the depth test, on real data and a steep
/// crafted field (16-bit and float heights).
#[test]
fn gradient_map_shading_matches_height_fetches() {
    let device = gpu();
    let ps = load::load(&data("puget_sound/ps_height_1k.png"), &LoadOptions::default()).unwrap();
    let steep = field(129, 129, 2.0, |x, z| ((x as f32 * 0.3).sin() * (z as f32 * 0.2).cos()) * 40.0 + x as f32);
    for hf in [ps, steep] {
        let mut scene = Scene::new(&device, hf, 33, Some(Sun::DEFAULT));
        for cam in &shading_views(&scene.hf) {
            let new = scene.render(cam, None, &Shading::default());
            let old = scene.render(cam, None, &Shading { normals: NormalSource::Heights, ..Shading::default() });
            let (rmse, share) = image_difference(&new, &old);
            println!(
                "{}: gradient map vs height fetches: RMSE {rmse:.4}, {:.4}% off by > 16",
                scene.hf.source,
                share * 100.0
            );
            assert_eq!(new.len(), old.len(), "image sizes");
            let off: Vec<_> = (new.chunks(4).zip(old.chunks(4)).enumerate())
                .filter(|(_, (n, o))| (0..3).any(|c| (n[c] as i32 - o[c] as i32).abs() > 16))
                .map(|(i, (n, o))| (i % 320, i / 320, n[..3].to_vec(), o[..3].to_vec()))
                .collect();
            println!("  pixels off by > 16 (x, y, new, old): {off:?}");
            assert!(rmse < 0.5, "{}: RMSE {rmse}", scene.hf.source);
            assert_eq!(share, 0.0);
            // The sky, drawn last, fills exactly the pixels no terrain covers, and leaves
            // every terrain pixel as it was.
            let bare = scene.render(cam, None, &plain());
            let (mut sky, mut terrain) = (0, 0);
            assert_eq!(new.len(), bare.len(), "image sizes");
            for (n, b) in new.chunks(4).zip(bare.chunks(4)) {
                if b[..3] == MAGENTA {
                    sky += 1;
                    assert_ne!(n[..3], MAGENTA);
                } else {
                    terrain += 1;
                    assert_eq!(n, b, "a terrain pixel changed under the sky pass");
                }
            }
            assert!(sky > 0 && terrain > 0, "sky {sky}, terrain {terrain}");
        }
        drop(scene);
    }
    finish(device);
}

/// Deferred shading (the default: the blocks write depth, one pass shades each pixel
/// from it) gives forward shading's image: the surface point recovered from depth is the
/// one interpolated from the vertices. Views far, oblique and close to the ground (where
/// triangles are large and silhouettes cut across the 2x2 quads the derivatives come
/// from), over real data and a steep crafted field, with the sky and the plain background.
#[test]
fn deferred_shading_matches_forward() {
    let device = gpu();
    let ps = load::load(&data("puget_sound/ps_height_1k.png"), &LoadOptions::default()).unwrap();
    let steep = field(129, 129, 2.0, |x, z| ((x as f32 * 0.3).sin() * (z as f32 * 0.2).cos()) * 40.0 + x as f32);
    // Embedded in a 129 x 129 grid: the margin beyond x = 99 and z = 69 is drawn, and
    // must not show (clipped by the depth pass, discarded by the forward one).
    let margin = field(100, 70, 2.0, |x, z| ((x as f32 * 0.2).sin() + (z as f32 * 0.3).cos()) * 6.0 + 20.0);
    for (hf, has_margin) in [(ps, false), (steep, false), (margin, true)] {
        let (wx, wz) = hf.world_extent();
        let top = hf.raw.iter().cloned().fold(f32::MIN, f32::max) * hf.height_scale;
        let ground = hf.surface_height(wx * 0.5, wz * 0.6);
        let [gw, gh] = hf.grid();
        assert_eq!((gw - 1) as f32 * hf.spacing.x > wx || (gh - 1) as f32 * hf.spacing.z > wz, has_margin);
        let mut scene = Scene::new(&device, hf, 33, Some(Sun::DEFAULT));
        // First: over the far corner, looking down at the true extent's far edges.
        let mut cams = vec![Camera::look_at(
            Vec3::new(wx * 0.9, top + wx * 0.5, wz * 0.9),
            Vec3::new(wx, 0.0, wz),
            60.0,
            320,
            240,
            0.1,
        )];
        cams.extend(shading_views(&scene.hf));
        // Close to the ground, looking along it.
        cams.push(Camera::look_at(
            Vec3::new(wx * 0.5, ground + wx * 0.01, wz * 0.6),
            Vec3::new(wx * 0.5, ground, wz * 0.3),
            60.0,
            320,
            240,
            0.1,
        ));
        for (i, cam) in cams.iter().enumerate() {
            for background in [Shading::default(), plain()] {
                let deferred = scene.render(cam, None, &background);
                let forward = scene.render(cam, None, &Shading { pixels: PixelPass::Forward, ..background });
                let (rmse, share) = image_difference(&deferred, &forward);
                println!(
                    "{}: deferred vs forward (sky {}): RMSE {rmse:.4}, {:.4}% off by > 16",
                    scene.hf.source,
                    background.sky,
                    share * 100.0
                );
                assert!(rmse < 0.5, "{}: RMSE {rmse}", scene.hf.source);
                // The margin's edge is decided by a clip distance in one and a discard in
                // the other: a pixel centre on it may fall either way.
                assert!(share <= 1e-4, "{}: {share} of the pixels off by more than 16 levels", scene.hf.source);
                // Background pixels are exactly the forward ones (no terrain drawn there).
                let keyed = |px: &[u8]| px.chunks(4).filter(|p| p[..3] == MAGENTA).count();
                if !background.sky {
                    let n = deferred.len() / 4;
                    assert!(keyed(&deferred).abs_diff(keyed(&forward)) * 10_000 <= n, "background differs");
                    // Over the far corner, the background shows where the margin lies.
                    assert!(!has_margin || i > 0 || keyed(&deferred) > 5000, "{} background pixels", keyed(&deferred));
                }
            }
        }
        drop(scene);
    }
    finish(device);
}

/// Telephoto views from far away: deferred shading recovers positions from 32-bit depth,
/// off by about 6e-8 of the distance, so from beyond `DEFERRED_MAX_SPACINGS` sample
/// spacings frames are shaded forward. A plateau's cliffs seen from 10^6 spacings with a
/// narrow field of view (an adversarial review's case: RMSE 1.66 when shaded deferred),
/// and nearer, where deferred stays within the claim.
#[test]
fn far_telephoto_views_match_forward() {
    let device = gpu();
    let plateau =
        field(129, 129, 1.0, |x, z| if (20..110).contains(&x) && (20..110).contains(&z) { 50.0 } else { 0.0 });
    let mut scene = Scene::new(&device, plateau, 33, Some(Sun::DEFAULT));
    for d in [3e4f32, 1e6] {
        let cam = Camera::look_at(Vec3::new(64.0, d, -d), Vec3::new(64.0, 40.0, 20.0), 0.005 * 1e6 / d, 320, 240, 0.05);
        let deferred = scene.render(&cam, None, &Shading::default());
        let forward = scene.render(&cam, None, &Shading { pixels: PixelPass::Forward, ..Shading::default() });
        let (rmse, share) = image_difference(&deferred, &forward);
        println!("from {d}: deferred vs forward RMSE {rmse:.4}, {:.4}% off by > 16", share * 100.0);
        assert!(rmse < 0.5 && share <= 1e-4, "from {d}: RMSE {rmse}, share {share}");
        let bare = scene.render(&cam, None, &plain());
        let terrain = bare.chunks(4).filter(|p| p[..3] != MAGENTA).count();
        assert!(terrain * 2 > bare.len() / 4, "from {d} the plateau fills most of the view ({terrain} pixels)");
    }
    drop(scene);
    finish(device);
}

/// Each shading switch is a specialization constant, compiled into its own pipeline
/// (llvmpipe would otherwise run every path a uniform decides, for every pixel). Each
/// variant must render under validation and take its own path: a pure red base texture
/// makes every terrain pixel red, a pure blue detail texture at weight 0 makes it blue, the
/// LOD tint moves the colours, and wireframe shows the background between its lines.
#[test]
fn every_shading_variant_takes_its_own_path() {
    let device = gpu();
    let hf = field(129, 129, 2.0, |x, z| ((x as f32 * 0.2).sin() * (z as f32 * 0.15).cos()) * 20.0 + 30.0);
    let (wx, wz) = hf.world_extent();
    let cam =
        Camera::look_at(Vec3::new(wx * 0.5, 150.0, wz * 1.1), Vec3::new(wx * 0.5, 0.0, wz * 0.4), 60.0, 160, 120, 0.1);
    let mm = MinMaxPyramid::build(&hf);
    let layout = BlockLayout::of(&hf, 33).unwrap();
    let target = Target::new(&device, cam.width, cam.height).unwrap();
    let solid = |rgb: [u8; 3]| Texture { width: 2, height: 2, rgba: [rgb[0], rgb[1], rgb[2], 255].repeat(4) };
    let render_from = |cam: &Camera, base: Option<&Texture>, detail: Option<&Texture>, shading: &Shading| {
        let blocks = traverse(&hf, &mm, &BlockCaches::default(), &layout, cam, LodSelect::Full).blocks;
        let terrain = TerrainGpu::new(&device, &hf, &mm, base, detail).unwrap();
        let mut r = BlocksRenderer::new(&device, &hf, &terrain, layout, COLOR_FORMAT, 1, None).unwrap();
        r.render_offscreen(&hf, &terrain, &target, cam, &blocks, shading).unwrap().0
    };
    let render = |base: Option<&Texture>, detail: Option<&Texture>, shading: &Shading| -> Vec<u8> {
        render_from(&cam, base, detail, shading)
    };
    let default = render(None, None, &plain());
    let terrain: Vec<usize> = (0..default.len() / 4).filter(|&i| default[4 * i..4 * i + 3] != MAGENTA).collect();
    assert!(terrain.len() > default.len() / 4 / 3, "only {} terrain pixels", terrain.len());
    let rgb = |px: &[u8], i: usize| [px[4 * i], px[4 * i + 1], px[4 * i + 2]];

    let red = render(Some(&solid([255, 0, 0])), None, &plain());
    assert!(terrain.iter().all(|&i| matches!(rgb(&red, i), [r, 0, 0] if r > 0)), "base texture not used");
    let blue = render(Some(&solid([255, 0, 0])), Some(&solid([0, 0, 255])), &Shading { detail_weight: 0.0, ..plain() });
    assert!(terrain.iter().all(|&i| matches!(rgb(&blue, i), [0, 0, b] if b > 0)), "detail texture not used");

    let tinted = render(None, None, &Shading { colour_by_lod: true, ..plain() });
    let moved: f64 = terrain
        .iter()
        .map(|&i| (0..3).map(|c| (tinted[4 * i + c] as f64 - default[4 * i + c] as f64).abs()).sum::<f64>())
        .sum::<f64>()
        / terrain.len() as f64;
    assert!(moved > 30.0, "the LOD tint moved the colours by {moved:.1} levels on average");

    if device.features.wireframe {
        // Close up, so that cells span many pixels.
        let near = Camera::look_at(
            Vec3::new(wx * 0.5, 60.0, wz * 0.6),
            Vec3::new(wx * 0.5, 0.0, wz * 0.4),
            60.0,
            160,
            120,
            0.1,
        );
        let (filled, wire) = (
            render_from(&near, None, None, &plain()),
            render_from(&near, None, None, &Shading { wireframe: true, ..plain() }),
        );
        let terrain: Vec<usize> = (0..filled.len() / 4).filter(|&i| filled[4 * i..4 * i + 3] != MAGENTA).collect();
        let background = terrain.iter().filter(|&&i| rgb(&wire, i) == MAGENTA).count();
        assert!(
            background > terrain.len() / 10 && background < terrain.len(),
            "wireframe: {background} of {} terrain pixels show the background",
            terrain.len()
        );
    } else {
        println!("note: no wireframe (fillModeNonSolid) on this device; that variant was not drawn");
    }
    drop(target);
    finish(device);
}

/// The shoreline moves continuously with the surface: a camera moved sideways by a fifth
/// of a pixel over a straight diagonal coast (sea at the lowest height, land rising
/// steeply beside it) changes no pixel by more than 16 levels. Water decided per quad
/// of samples (a step at the quads' edges) flipped the pixels along the coast between
/// land and water; that was most of a morphing frame's visible change (README, popping).
#[test]
fn shoreline_moves_continuously() {
    let device = gpu();
    let hf = field(129, 129, 10.0, |x, z| ((x as f32 - 40.0 - 0.37 * z as f32) * 3.0).max(0.0));
    let mut scene = Scene::new(&device, hf, 33, None);
    // About 0.7 pixels a metre at this height: 0.3 m is a fifth of a pixel.
    let at = |dx: f32| {
        let pos = Vec3::new(637.0 + dx, 300.0, 640.0);
        Camera::look_at(pos, pos + Vec3::new(0.0, -1.0, -0.3), 60.0, 320, 240, 1.0)
    };
    let (a, b) = (scene.render(&at(0.0), None, &plain()), scene.render(&at(0.3), None, &plain()));
    let water = |px: &[u8]| px[2] as i32 > px[0] as i32 + 40 && px[2] as i32 > px[1] as i32 + 15;
    let n = a.len() / 4;
    let wet = (0..n).filter(|&i| water(&a[4 * i..4 * i + 3])).count();
    assert!(wet > n / 10 && wet < n * 9 / 10, "the view shows {wet} water pixels of {n}: not a coast");
    let jumps: Vec<usize> =
        (0..n).filter(|&i| (0..3).any(|c| (a[4 * i + c] as i32 - b[4 * i + c] as i32).abs() > 16)).collect();
    assert!(jumps.is_empty(), "{} pixels jumped by more than 16 levels, e.g. pixel {:?}", jumps.len(), jumps.first());
    drop(scene);
    finish(device);
}

/// Water is at or below 0 m when heights are metres above sea level, never "the lowest
/// sample": an inland plateau (lowest ground 200 m) shows no water when its heights are
/// absolute, and its lowest ground is water when they are only relative; a coast that
/// dips below 0 m shows water exactly where the ground is at or below 0 m.
#[test]
fn water_is_at_sea_level_when_heights_are_absolute() {
    let device = gpu();
    let water = |px: &[u8]| px[2] as i32 > px[0] as i32 + 40 && px[2] as i32 > px[1] as i32 + 15;
    let wet = |img: &[u8]| (0..img.len() / 4).filter(|&i| water(&img[4 * i..4 * i + 3])).count();
    let cam = {
        let pos = Vec3::new(640.0, 900.0, 640.0);
        Camera::look_at(pos, pos + Vec3::new(0.0, -1.0, -0.01), 70.0, 160, 120, 1.0)
    };
    // A plateau: half of it level at 200 m, the other half rising to 600 m.
    let plateau = |absolute: bool| {
        let mut hf = field(129, 129, 10.0, |x, _| 200.0 + (x as f32 - 64.0).max(0.0) * 6.0);
        hf.georef.absolute_heights = absolute;
        hf
    };
    let mut relative = Scene::new(&device, plateau(false), 33, None);
    let rel = wet(&relative.render(&cam, None, &plain()));
    drop(relative);
    let mut absolute = Scene::new(&device, plateau(true), 33, None);
    let abs = wet(&absolute.render(&cam, None, &plain()));
    drop(absolute);
    let n = 160 * 120;
    assert!(rel > n / 4, "relative heights: the lowest ground should be water ({rel} of {n} pixels)");
    assert_eq!(abs, 0, "absolute heights at 200 m and above: no water, found {abs} pixels");
    // A coast: a level seabed 5 m below 0 on the left half, land rising from 5 m on the
    // right: water on the left only.
    let mut coast = field(129, 129, 10.0, |x, _| if x < 64 { -5.0 } else { 5.0 + (x as f32 - 64.0) * 2.0 });
    coast.georef.absolute_heights = true;
    let mut scene = Scene::new(&device, coast, 33, None);
    let img = scene.render(&cam, None, &plain());
    let vp = cam.view_proj();
    let (mut sea, mut land) = ((0, 0), (0, 0)); // (wet, seen)
    for z in (4..125).step_by(6) {
        for x in (2..127).step_by(3) {
            if (61..=66).contains(&x) {
                continue; // the shoreline blends over the quad at the coast
            }
            let p =
                Vec3::new(x as f32 * 10.0, if x < 64 { -5.0 } else { 5.0 + (x as f32 - 64.0) * 2.0 }, z as f32 * 10.0);
            let Some((px, py)) = cam.project(&vp, p) else { continue };
            if !(0.0..160.0).contains(&px) || !(0.0..120.0).contains(&py) {
                continue;
            }
            let i = ((py as usize) * 160 + px as usize) * 4;
            let c = if x < 64 { &mut sea } else { &mut land };
            c.0 += water(&img[i..i + 3]) as usize;
            c.1 += 1;
        }
    }
    assert!(sea.1 > 100 && land.1 > 100, "points seen: sea {}, land {}", sea.1, land.1);
    assert_eq!(sea.0, sea.1, "the sea 5 m below 0 is not all water");
    assert_eq!(land.0, 0, "land above 0 m shaded as water at {} of {} points", land.0, land.1);
    drop(scene);
    finish(device);
}

/// `--voids hole`: a void region shows what is behind it (here the background), in both
/// pixel passes (deferred shading falls back to forward), and nothing else changes: the
/// same view with the voids filled shows terrain there.
#[test]
fn voids_drawn_as_holes_show_the_background() {
    let device = gpu();
    let void = |x: usize, z: usize| (40..80).contains(&x) && (50..90).contains(&z);
    let make = |holes: bool| {
        let mut hf = field(129, 129, 10.0, |x, z| ((x as f32 * 0.1).sin() + (z as f32 * 0.07).cos()) * 20.0);
        if holes {
            hf.void_mask = Some((0..129 * 129).map(|i| void(i % 129, i / 129)).collect());
        }
        hf
    };
    let cam = {
        let pos = Vec3::new(640.0, 1400.0, 700.0);
        Camera::look_at(pos, pos + Vec3::new(0.0, -1.0, -0.01), 60.0, 160, 120, 1.0)
    };
    let vp = cam.view_proj();
    let mut seen = Vec::new();
    for holes in [false, true] {
        let mut scene = Scene::new(&device, make(holes), 33, None);
        for pixels in [PixelPass::Deferred, PixelPass::Forward] {
            let img = scene.render(&cam, None, &Shading { pixels, ..plain() });
            let (mut inside, mut outside) = ((0, 0), (0, 0)); // (background, seen)
            for z in (2..127).step_by(4) {
                for x in (2..127).step_by(4) {
                    // Keep clear of the hole's edge, where the bilinear share decides.
                    let near_edge = (38..=42).contains(&x)
                        || (78..=82).contains(&x)
                        || (48..=52).contains(&z)
                        || (88..=92).contains(&z);
                    if near_edge {
                        continue;
                    }
                    let p = Vec3::new(x as f32 * 10.0, 0.0, z as f32 * 10.0);
                    let Some((px, py)) = cam.project(&vp, p) else { continue };
                    if !(0.0..160.0).contains(&px) || !(0.0..120.0).contains(&py) {
                        continue;
                    }
                    let c = pixel(&img, 160, px as u32, py as u32);
                    let bucket = if void(x, z) { &mut inside } else { &mut outside };
                    bucket.0 += (c == MAGENTA) as usize;
                    bucket.1 += 1;
                }
            }
            assert!(inside.1 > 30 && outside.1 > 100, "{inside:?} {outside:?}");
            assert_eq!(outside.0, 0, "holes {holes}, {pixels:?}: background outside the voids");
            seen.push((holes, pixels, inside));
        }
        drop(scene);
    }
    for (holes, pixels, (bg, n)) in seen {
        let want = if holes { n } else { 0 };
        assert_eq!(bg, want, "holes {holes}, {pixels:?}: {bg} of {n} points inside the voids show the background");
    }
    finish(device);
}

/// Vertical exaggeration keeps the terrain's images: a heightfield drawn at three times
/// its height scale over images made at its own scale (the viewer's live control: the
/// gradient map and sea level scale with the height scale) renders as the same samples
/// loaded at three times the scale, in both pixel passes.
#[test]
fn exaggeration_renders_as_the_scaled_heightfield() {
    let device = gpu();
    let samples = |x: usize, z: usize| ((x as f32 * 0.21).sin() * (z as f32 * 0.13).cos()) * 40.0 + (x as f32 * 0.2);
    // A low sun: the shadows and occlusion at three times the heights differ from the
    // heightfield's own (the lighting map must be redrawn).
    let sun = Some(Sun { azimuth: 100.0, elevation: 20.0 });
    let base = field(129, 129, 10.0, samples);
    let mut scaled = base.clone();
    scaled.height_scale = 3.0;
    let cam = Camera::look_at(Vec3::new(-200.0, 400.0, 700.0), Vec3::new(640.0, 0.0, 640.0), 60.0, 200, 150, 1.0);
    // Images made at the heightfield's own scale, frames drawn at three times it.
    let mm = MinMaxPyramid::build(&base);
    let layout = BlockLayout::of(&base, 33).unwrap();
    let terrain = Arc::new(TerrainGpu::new(&device, &base, &mm, None, None).unwrap());
    // Made for the heightfield as loaded, then its lighting redrawn at the new scale, as
    // the viewer does.
    let mut renderer = BlocksRenderer::new(&device, &base, &terrain, layout, COLOR_FORMAT, 1, sun).unwrap();
    renderer.redraw_lighting(&scaled).unwrap();
    let t = traverse(&scaled, &mm, &BlockCaches::default(), &layout, &cam, LodSelect::Full);
    let mut want = Scene::new(&device, scaled.clone(), 33, sun);
    for pixels in [PixelPass::Deferred, PixelPass::Forward] {
        let target = Target::new(&device, cam.width, cam.height).unwrap();
        let shading = Shading { pixels, ..plain() };
        let (got, _) = renderer.render_offscreen(&scaled, &terrain, &target, &cam, &t.blocks, &shading).unwrap();
        let reference = want.render(&cam, None, &shading);
        let worst = got.iter().zip(&reference).map(|(a, b)| (*a as i32 - *b as i32).abs()).max().unwrap();
        assert_eq!(got.len(), reference.len());
        let terrain_px = (0..got.len() / 4).filter(|&i| got[4 * i..4 * i + 3] != MAGENTA).count();
        println!("{pixels:?}: {terrain_px} terrain pixels, worst difference {worst} levels");
        assert!(terrain_px > got.len() / 8, "{pixels:?}: only {terrain_px} terrain pixels");
        assert!(worst <= 1, "{pixels:?}: exaggerated frame differs from the scaled heightfield by {worst} levels");
    }
    drop((renderer, terrain, want));
    finish(device);
}

/// The sky is one smooth gradient from 1 m to 10^6 m above the terrain, in both pixel
/// passes: down a column of sky no two neighbouring rows differ by more than 3 levels
/// (the gradient spans about 80 over the frame, one level per row at most), and it does change. The ray of a
/// sky pixel used to be unprojected at depth 0.5, two near planes from the camera, and the
/// camera's position subtracted from it in f32: at 10^4 to 10^5 m that quantized the ray
/// into a few flat bands with hard edges.
#[test]
fn the_sky_is_smooth_at_every_altitude() {
    let device = gpu();
    let hf = field(65, 65, 30.0, |x, z| ((x * 7 + z * 3) % 5) as f32);
    let near = vkterrain::lod::view::near_plane(&hf);
    let mut scene = Scene::new(&device, hf, 9, None);
    for pixels in [PixelPass::Deferred, PixelPass::Forward] {
        for altitude in [1.0f32, 1e2, 1e3, 1e4, 3e4, 1e5, 3e5, 1e6] {
            // Pitched 40 degrees up with a 60-degree field of view: every pixel is sky.
            let pos = Vec3::new(960.0, altitude, 960.0);
            let dir = Vec3::new(0.3, 40f32.to_radians().tan(), -1.0);
            let cam = Camera::look_at(pos, pos + dir, 60.0, 96, 240, near);
            let img = scene.render(&cam, None, &Shading { pixels, ..Shading::default() });
            let at = |x: usize, y: usize, c: usize| img[(y * 96 + x) * 4 + c] as i32;
            let mut largest_step = 0;
            for x in [10usize, 48, 85] {
                for y in 0..239 {
                    for c in 0..3 {
                        largest_step = largest_step.max((at(x, y + 1, c) - at(x, y, c)).abs());
                    }
                }
            }
            let span = (0..3).map(|c| (at(48, 0, c) - at(48, 239, c)).abs()).max().unwrap();
            println!("{pixels:?}, {altitude} m: largest step {largest_step}, span {span}");
            assert!(largest_step <= 3, "{pixels:?}, {altitude} m: the sky jumps by {largest_step} levels between rows");
            assert!(span >= 20, "{pixels:?}, {altitude} m: the sky is flat (top and bottom differ by {span})");
        }
    }
    drop(scene);
    finish(device);
}

/// Low views along the ground, level with the horizon or a few degrees below it: where
/// blocks far away carry more triangles than pixels (the ray-caster's case) and grazing
/// rays meet ridges and block edges.
fn horizon_poses(hf: &Heightfield, count: usize) -> Vec<Camera> {
    let (wx, wz) = hf.world_extent();
    (0..count)
        .map(|i| {
            let f = (i as f32 + 0.5) / count as f32;
            let x = wx * (0.1 + 0.8 * f);
            let z = wz * (0.1 + 0.8 * ((f * 7.3).fract()));
            let ground = hf.surface_height(x, z);
            let alt = hf.spacing.min() * (1.0 + 40.0 * ((f * 3.7).fract()));
            let pos = Vec3::new(x, ground + alt, z);
            let pitch = (12.0 * ((f * 5.1).fract())).to_radians();
            let yaw = f * std::f32::consts::TAU * 5.0;
            let dir = Vec3::new(yaw.cos() * pitch.cos(), -pitch.sin(), yaw.sin() * pitch.cos());
            Camera::look_at(pos, pos + dir, 50.0, 320, 240, hf.spacing.min() * 0.05)
        })
        .collect()
}

/// SPEC 10, the crack check: blocks drawn by the ray-caster (every other eligible block,
/// then all of them) leave no pixel showing background where the all-raster frame shows
/// terrain, at low, horizon-level views over real data and over knife-edge ridges and a
/// cliff, with error-driven (morphing and not) and distance selections. The images agree
/// up to rasterization rules. A ray-caster that skips the quads of one row of a block
/// (or that ray-casts blocks whose edges follow a coarser neighbour) fails it.
#[test]
fn raycast_blocks_leave_no_cracks() {
    let device = gpu();
    let ps = load::load(&data("puget_sound/ps_height_1k.png"), &LoadOptions::default()).unwrap();
    let ridges = field(257, 257, 1.0, |x, z| {
        let knife = if (x + 2 * z) % 23 == 0 { 25.0 } else { 0.0 };
        let cliff = if x > 150 { 40.0 } else { 0.0 };
        knife + cliff + (x as f32 * 0.05).sin() * 3.0 + (z as f32 * 0.11).cos() * 2.0
    });
    let (mut cast_blocks, mut frames) = (0u64, 0);
    let (mut worst_rmse, mut worst_share) = (0.0f64, 0.0f64);
    for hf in [ps, ridges] {
        let mut scene = Scene::new(&device, hf, 33, None);
        let activity = ErrorsActivity::start(&device, scene.terrain.clone(), scene.hf.clone(), scene.layout).unwrap();
        for cam in horizon_poses(&scene.hf, 24) {
            let gen = activity
                .wait_for(ErrorParams::new(&cam, ErrorMode::Strict), std::time::Duration::from_secs(120))
                .unwrap();
            let selections = [
                LodSelect::errors(&gen.errors, gen.params.camera, 1.0, ErrorMode::Strict).with_morph(false),
                LodSelect::errors(&gen.errors, gen.params.camera, 1.0, ErrorMode::Strict),
                LodSelect::Distance { factor: 2.0 },
            ];
            for select in selections {
                let (raster, stats) = scene.render_select(&cam, select, &plain());
                assert_eq!(stats.raycast_blocks, 0);
                for raycast in [Raycast::Checkerboard, Raycast::All] {
                    let (cast, stats) = scene.render_select(&cam, select, &Shading { raycast, ..plain() });
                    cast_blocks += stats.raycast_blocks;
                    frames += 1;
                    let holes = (raster.chunks(4).zip(cast.chunks(4)))
                        .filter(|(r, c)| r[..3] != MAGENTA && c[..3] == MAGENTA)
                        .count();
                    assert_eq!(
                        holes, 0,
                        "{}: {holes} pixels show background through ray-cast blocks ({raycast:?}, camera {:?})",
                        scene.hf.source, cam.position
                    );
                    // Silhouettes differ: the rasterizer snaps vertices to 1/256 of a pixel
                    // and the ray-caster lifts the surface by 1/16 (raycast.frag), and the
                    // deferred pass's derivatives change with them. Measured (printed at
                    // the end): at most 0.40 % of the pixels, RMSE 7.7, a low view whose
                    // horizon line moves by a pixel over a third of its length.
                    let (rmse, share) = image_difference(&raster, &cast);
                    (worst_rmse, worst_share) = (worst_rmse.max(rmse), worst_share.max(share));
                    assert!(rmse < 10.0, "{}: RMSE {rmse} ({raycast:?})", scene.hf.source);
                    assert!(share <= 0.01, "{}: {share} of the pixels differ by more than 16 levels", scene.hf.source);
                }
            }
        }
        // A camera under the surface sees through the culled undersides, which rays do
        // not reproduce: nothing is ray-cast there (found by review: a camera inside a
        // canyon wall showed 31 holes and 118 extra pixels).
        let (wx, wz) = scene.hf.world_extent();
        let ground = scene.hf.surface_height(wx * 0.5, wz * 0.5);
        let pos = Vec3::new(wx * 0.5, ground - scene.hf.spacing.min(), wz * 0.5);
        let under = Camera::look_at(pos, pos + Vec3::new(1.0, 0.0, 0.3), 50.0, 320, 240, 0.05);
        let (_, stats) = scene.render_select(
            &under,
            LodSelect::Distance { factor: 2.0 },
            &Shading { raycast: Raycast::All, ..plain() },
        );
        assert_eq!(stats.raycast_blocks, 0, "{}: ray-cast blocks with the camera under the surface", scene.hf.source);
        // Beyond the edge and lower than the top: rays can enter through the cut edge
        // (review: 11 holes 2 km off Puget Sound's edge at 900 m).
        // Above the edge under it (so not under the surface), below the terrain's top.
        let edge = scene.hf.surface_height(wx, wz * 0.5);
        let top = scene.hf.raw.iter().cloned().fold(f32::MIN, f32::max) * scene.hf.height_scale;
        assert!(top > edge + 1.0, "{}: the edge is the top", scene.hf.source);
        let pos = Vec3::new(wx * 1.05, (edge + top) * 0.5, wz * 0.5);
        let beyond = Camera::look_at(pos, Vec3::new(wx * 0.5, edge, wz * 0.5), 50.0, 320, 240, 0.05);
        let (_, stats) = scene.render_select(
            &beyond,
            LodSelect::Distance { factor: 2.0 },
            &Shading { raycast: Raycast::All, ..plain() },
        );
        assert_eq!(stats.raycast_blocks, 0, "{}: ray-cast blocks seen through the cut edge", scene.hf.source);
        drop(activity);
        drop(scene);
    }
    println!(
        "{frames} frames, {cast_blocks} blocks ray-cast; worst RMSE {worst_rmse:.2}, worst share off by > 16 levels {:.3} %",
        worst_share * 100.0
    );
    assert!(cast_blocks > 1000, "only {cast_blocks} blocks were ray-cast");
    finish(device);
}
