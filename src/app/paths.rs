//! The benchmark's and the quality sweep's camera paths.

use crate::lod::camera::Camera;
use crate::lod::heightfield::Heightfield;
use crate::lod::pyramid::MinMaxPyramid;
use crate::lod::view::near_plane;
use clap::ValueEnum;
use glam::Vec3;

#[derive(Clone, Copy, Debug, PartialEq, Eq, ValueEnum)]
pub enum CameraPath {
    /// From the centre of the south edge straight to the centre of the north edge at
    /// 3600 km/h (simulated), 5% of the terrain's size above its highest sample,
    /// pitched down so that the far edge is just inside the top of the view.
    PaperFlyover,
    /// A stationary full turn above the terrain's centre, pitched 20 degrees down.
    Rotate360,
}

/// What a camera path needs of a terrain: its world extent from the origin, the world
/// heights it spans, the ground under its centre, and the near plane for its spacing.
#[derive(Clone, Copy, Debug)]
pub struct PathTerrain {
    pub extent: (f32, f32),
    pub heights: [f32; 2],
    pub centre_ground: f32,
    pub near: f32,
}

impl PathTerrain {
    pub fn of(hf: &Heightfield, mm: &MinMaxPyramid) -> Self {
        let (wx, wz) = hf.world_extent();
        PathTerrain {
            extent: (wx, wz),
            heights: mm.range().map(|r| r * hf.height_scale),
            centre_ground: hf.surface_height(wx * 0.5, wz * 0.5),
            near: near_plane(hf),
        }
    }
}

/// Camera and simulated time of frame `i` of `n`.
pub fn path_camera(
    hf: &Heightfield,
    mm: &MinMaxPyramid,
    path: CameraPath,
    i: u64,
    n: u64,
    fovy: f32,
    size: (u32, u32),
) -> (Camera, f64) {
    path_camera_over(&PathTerrain::of(hf, mm), path, i, n, fovy, size)
}

/// [`path_camera`] over a terrain known by its [`PathTerrain`] (a streamed archive).
pub fn path_camera_over(
    terrain: &PathTerrain,
    path: CameraPath,
    i: u64,
    n: u64,
    fovy: f32,
    size: (u32, u32),
) -> (Camera, f64) {
    let (wx, wz) = terrain.extent;
    let l = wx.max(wz);
    let [bottom, top] = terrain.heights;
    let near = terrain.near;
    let f = if n > 1 { i as f64 / (n - 1) as f64 } else { 0.0 };
    match path {
        CameraPath::PaperFlyover => {
            let alt = top + 0.05 * l;
            let duration = wz as f64 / 1000.0; // 3600 km/h = 1000 m/s
            let t = f * duration;
            let pos = Vec3::new(wx * 0.5, alt, wz - (t * 1000.0) as f32);
            // Far edge 5% of the field of view below the top of the image.
            let below = ((alt - bottom) / wz).atan();
            let pitch = below + fovy.to_radians() * 0.45;
            let dir = Vec3::new(0.0, -pitch.sin(), -pitch.cos());
            (Camera::look_at(pos, pos + dir, fovy, size.0, size.1, near), t)
        }
        CameraPath::Rotate360 => {
            let pos = Vec3::new(wx * 0.5, terrain.centre_ground.max(top * 0.5) + 0.03 * l, wz * 0.5);
            let yaw = f as f32 * std::f32::consts::TAU;
            let pitch = 20f32.to_radians();
            let dir = Vec3::new(yaw.cos() * pitch.cos(), -pitch.sin(), yaw.sin() * pitch.cos());
            // 10 degrees per simulated second.
            (Camera::look_at(pos, pos + dir, fovy, size.0, size.1, near), f * 36.0)
        }
    }
}
