//! The default ways to look at a terrain: the near plane for its sample spacing, and a
//! view of the whole of it.

use crate::lod::camera::Camera;
use crate::lod::heightfield::Heightfield;
use glam::Vec3;

/// Near plane: a hundred-thousandth of the sample spacing, at most 1 cm (1.6 mm on Puget
/// Sound 1k), so that a camera half a metre over any ground, steep slopes and cliffs
/// included, still sees the ground at its feet (a terrain point closer than this is
/// clipped). Reversed infinite Z in a float depth buffer keeps the same relative depth
/// precision for any near plane, so nothing is lost far away; the error passes clamp
/// distances to it, so the blocks right around such a camera are drawn at full
/// resolution, as they must be.
pub fn near_plane(hf: &Heightfield) -> f32 {
    near_plane_for(hf.spacing.min())
}

/// [`near_plane`] for the smaller of a terrain's two sample spacings.
pub fn near_plane_for(spacing: f32) -> f32 {
    (spacing * 1e-5).min(0.01)
}

/// Above the south edge looking at the terrain's centre, backed away along that
/// direction until the whole terrain (its bounding box) fits in the frame; of a strip
/// more than [`MAX_ASPECT`] times longer than wide, its middle part that long.
pub fn default_view(hf: &Heightfield, fovy_deg: f32, width: u32, height: u32) -> (Vec3, Vec3) {
    let (wx, wz) = hf.world_extent();
    let (lo, hi) = hf.raw.iter().fold((f32::INFINITY, f32::NEG_INFINITY), |(a, b), &v| (a.min(v), b.max(v)));
    let heights = [lo * hf.height_scale, hi * hf.height_scale];
    view_of_box([wx, wz], heights, fovy_deg, width, height, near_plane(hf))
}

/// The longest side [`view_of_box`] frames, in widths of the terrain.
pub const MAX_ASPECT: f32 = 4.0;

/// [`default_view`] of a terrain known by its world extent `[wx, wz]` (from the origin)
/// and its world height range: a streamed archive, whose samples are not all in memory.
pub fn view_of_box(
    extent: [f32; 2],
    heights: [f32; 2],
    fovy_deg: f32,
    width: u32,
    height: u32,
    near: f32,
) -> (Vec3, Vec3) {
    let [ex, ez] = extent;
    // A strip longer than MAX_ASPECT times its width is framed by its middle part only:
    // the whole of it would be a line a pixel or two thick.
    let [wx, wz] = [ex.min(MAX_ASPECT * ez), ez.min(MAX_ASPECT * ex)];
    let (x0, z0) = ((ex - wx) * 0.5, (ez - wz) * 0.5);
    let l = wx.max(wz);
    let [bottom, top] = heights;
    let target = Vec3::new(ex * 0.5, bottom, ez * 0.5);
    // About 35 degrees down, from the south.
    let dir = Vec3::new(0.0, 0.7, 1.0).normalize();
    let corners: Vec<Vec3> = (0..8)
        .map(|i| {
            Vec3::new(
                x0 + if i & 1 == 0 { 0.0 } else { wx },
                if i & 2 == 0 { bottom } else { top },
                z0 + if i & 4 == 0 { 0.0 } else { wz },
            )
        })
        .collect();
    let mut dist = 0.3 * l + (top - bottom);
    for _ in 0..200 {
        let pos = target + dir * dist;
        let cam = Camera::look_at(pos, target, fovy_deg, width, height, near);
        let vp = cam.view_proj();
        let fits = corners.iter().all(|&c| {
            cam.project(&vp, c).is_some_and(|(x, y)| {
                let (fx, fy) = (x / width as f32, y / height as f32);
                (0.03..=0.97).contains(&fx) && (0.03..=0.97).contains(&fy)
            })
        });
        if fits {
            return (pos, target);
        }
        dist *= 1.05;
    }
    (target + dir * dist, target)
}

/// The viewers' default haze (exponential fog density) for a terrain `size` world units
/// across.
pub fn default_fog(size: f32) -> f32 {
    0.2 / size
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Where the box's corners land on a 640 x 480 frame from `view_of_box`'s camera.
    fn projected(extent: [f32; 2], heights: [f32; 2], window: [f32; 4]) -> Vec<(f32, f32)> {
        let (pos, target) = view_of_box(extent, heights, 45.0, 640, 480, 0.01);
        let cam = Camera::look_at(pos, target, 45.0, 640, 480, 0.01);
        let vp = cam.view_proj();
        let [x0, z0, x1, z1] = window;
        (0..8)
            .map(|i| {
                let c = Vec3::new(
                    if i & 1 == 0 { x0 } else { x1 },
                    heights[(i >> 1) & 1],
                    if i & 4 == 0 { z0 } else { z1 },
                );
                cam.project(&vp, c).expect("in front of the camera")
            })
            .collect()
    }

    fn inside(p: &[(f32, f32)]) -> bool {
        p.iter().all(|&(x, y)| (0.0..=640.0).contains(&x) && (0.0..=480.0).contains(&y))
    }

    /// A square terrain is seen whole; a 16400 x 40 strip (a reviewer's raster, a line
    /// two pixels thick when seen whole) is framed by its middle 160 x 40, which fills a
    /// good share of the frame; the same along z.
    #[test]
    fn strips_are_framed_by_their_middle() {
        let square = projected([1000.0, 1000.0], [0.0, 200.0], [0.0, 0.0, 1000.0, 1000.0]);
        assert!(inside(&square), "{square:?}");
        for (extent, window) in
            [([16400.0, 40.0], [8120.0, 0.0, 8280.0, 40.0]), ([40.0, 16400.0], [0.0, 8120.0, 40.0, 8280.0])]
        {
            let p = projected(extent, [0.0, 10.0], window);
            assert!(inside(&p), "{extent:?}: {p:?}");
            let (ys, xs): (Vec<f32>, Vec<f32>) = (p.iter().map(|c| c.1).collect(), p.iter().map(|c| c.0).collect());
            let span =
                |v: &[f32]| v.iter().cloned().fold(f32::MIN, f32::max) - v.iter().cloned().fold(f32::MAX, f32::min);
            assert!(
                span(&xs) > 320.0 || span(&ys) > 240.0,
                "{extent:?}: the middle spans {} x {} px",
                span(&xs),
                span(&ys)
            );
            assert!(span(&ys) > 60.0, "{extent:?}: {} px high", span(&ys));
        }
    }
}
