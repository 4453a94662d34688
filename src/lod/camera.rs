//! Camera, projection (reversed infinite Z, Vulkan clip space) and frustum culling.

use glam::{Mat4, Vec3, Vec4};

#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Camera {
    pub position: Vec3,
    /// Unit view direction.
    pub forward: Vec3,
    /// Vertical field of view, radians.
    pub fovy: f32,
    pub width: u32,
    pub height: u32,
    /// Near plane distance, world units.
    pub near: f32,
}

impl Camera {
    pub fn look_at(position: Vec3, target: Vec3, fovy_deg: f32, width: u32, height: u32, near: f32) -> Self {
        let forward = (target - position).try_normalize().unwrap_or(Vec3::NEG_Z);
        Camera { position, forward, fovy: fovy_deg.to_radians(), width, height, near }
    }

    pub fn aspect(&self) -> f32 {
        self.width as f32 / self.height as f32
    }

    /// Camera basis (right, up) for the current forward. Looking (nearly) straight down
    /// or up, the screen's up is north (-z), which is where it tends for a view tilted
    /// north: the picture does not turn over as the view passes that threshold.
    pub fn basis(&self) -> (Vec3, Vec3) {
        let world_up = if self.forward.y.abs() > 0.999 { Vec3::NEG_Z } else { Vec3::Y };
        let right = self.forward.cross(world_up).normalize();
        (right, right.cross(self.forward))
    }

    pub fn view(&self) -> Mat4 {
        let (_, up) = self.basis();
        // From the direction itself: `position + forward` rounds to the f32 grid at the
        // position's magnitude, which at 70 km turned the view by 0.002 rad (3 pixels
        // at the frame's edge between the image and the culling frustum).
        Mat4::look_to_rh(self.position, self.forward, up)
    }

    /// Reversed infinite perspective with Vulkan's y-down clip space.
    pub fn proj(&self) -> Mat4 {
        let mut p = Mat4::perspective_infinite_reverse_rh(self.fovy, self.aspect(), self.near);
        p.y_axis.y = -p.y_axis.y;
        p
    }

    pub fn view_proj(&self) -> Mat4 {
        self.proj() * self.view()
    }

    /// Pixels per unit of tangent: `viewport_height / (2 tan(fovy / 2))` (SPEC section 3).
    pub fn kappa(&self) -> f32 {
        self.height as f32 / (2.0 * (self.fovy * 0.5).tan())
    }

    /// `1 / cos^2(theta_max)`, theta_max being half the diagonal field of view.
    pub fn inv_cos2_max(&self) -> f32 {
        let t = (self.fovy * 0.5).tan();
        1.0 + t * t * (1.0 + self.aspect() * self.aspect())
    }

    /// `1 / cos^2(theta_b)`, `theta_b` the largest off-axis angle of the box `[min, max]`
    /// seen from the camera (SPEC section 3): what the projection can magnify a world
    /// deviation inside the box by. The two screen tangents `x/z`, `y/z` are extreme at
    /// corners of a box in front of the eye. They are clamped to the frustum's widened by
    /// `margin_px / kappa`: a visible sample lies inside the frustum, and as long as its
    /// drawn point stays within `margin_px` pixels of it (what the caller then checks
    /// against `margin_px`), every point between the two projects within that widened
    /// frustum. Without the widening a deviation leaving the frustum near its edge, where
    /// the gnomonic projection magnifies most, escapes the bound.
    pub fn inv_cos2_aabb(&self, min: Vec3, max: Vec3, margin_px: f32) -> f32 {
        let (right, up) = self.basis();
        let widen = margin_px / self.kappa();
        let tv = (self.fovy * 0.5).tan() + widen;
        let th = (self.fovy * 0.5).tan() * self.aspect() + widen;
        let limit = 1.0 + th * th + tv * tv;
        let (mut worst, mut tx, mut ty) = (1.0f32, 0.0f32, 0.0f32);
        for i in 0..8 {
            let c = Vec3::new(
                if i & 1 == 0 { min.x } else { max.x },
                if i & 2 == 0 { min.y } else { max.y },
                if i & 4 == 0 { min.z } else { max.z },
            );
            let v = c - self.position;
            let along = v.dot(self.forward);
            if along <= 0.0 {
                return limit;
            }
            // 1 / cos^2 = |v|^2 / along^2 = 1 + tan^2.
            worst = worst.max(v.length_squared() / (along * along));
            tx = tx.max(v.dot(right).abs() / along);
            ty = ty.max(v.dot(up).abs() / along);
        }
        let (tx, ty) = (tx.min(th), ty.min(tv));
        worst.min(1.0 + tx * tx + ty * ty).min(limit)
    }

    /// Largest `cos(beta)` over the box, `beta` the elevation of the ray from the eye to
    /// a point of the box. A deviation of the drawn surface is vertical, and only its part
    /// across the ray shows on screen: `|v| cos(beta)` for a vertical `v`. The ray is
    /// flattest at the largest horizontal distance and the smallest height difference.
    pub fn vertical_factor_aabb(&self, min: Vec3, max: Vec3) -> f32 {
        let p = self.position;
        let dy = (min.y - p.y).max(p.y - max.y).max(0.0);
        if dy == 0.0 {
            return 1.0;
        }
        let hx = (p.x - min.x).abs().max((max.x - p.x).abs());
        let hz = (p.z - min.z).abs().max((max.z - p.z).abs());
        let h2 = hx * hx + hz * hz;
        (h2 / (h2 + dy * dy)).sqrt()
    }

    /// Pixel coordinates (x right, y down) of a world point, or `None` behind the eye.
    pub fn project(&self, view_proj: &Mat4, p: Vec3) -> Option<(f32, f32)> {
        let c = *view_proj * p.extend(1.0);
        if c.w <= 1e-12 {
            return None;
        }
        Some(((c.x / c.w * 0.5 + 0.5) * self.width as f32, (c.y / c.w * 0.5 + 0.5) * self.height as f32))
    }

    pub fn frustum(&self) -> Frustum {
        self.frustum_widened(0.0)
    }

    /// The frustum with its four side planes moved `margin_px` pixels out beyond the
    /// image's edges (the near plane stays).
    pub fn frustum_widened(&self, margin_px: f32) -> Frustum {
        let (right, up) = self.basis();
        let tv = (self.fovy * 0.5).tan() * (1.0 + 2.0 * margin_px / self.height as f32);
        let th = (self.fovy * 0.5).tan() * self.aspect() * (1.0 + 2.0 * margin_px / self.width as f32);
        let f = self.forward;
        let normals = [
            (right + th * f).normalize(),
            (-right + th * f).normalize(),
            (up + tv * f).normalize(),
            (-up + tv * f).normalize(),
        ];
        let mut planes = [Vec4::ZERO; 5];
        for (i, n) in normals.iter().enumerate() {
            planes[i] = n.extend(-n.dot(self.position));
        }
        planes[4] = f.extend(-f.dot(self.position) - self.near);
        Frustum { planes }
    }
}

/// Inward-facing planes: left, right, bottom, top, near (the far plane is at infinity).
#[derive(Clone, Copy, Debug)]
pub struct Frustum {
    pub planes: [Vec4; 5],
}

impl Frustum {
    /// False only when the box is certainly outside (conservative).
    pub fn intersects_aabb(&self, min: Vec3, max: Vec3) -> bool {
        self.planes.iter().all(|p| {
            let v = Vec3::new(
                if p.x >= 0.0 { max.x } else { min.x },
                if p.y >= 0.0 { max.y } else { min.y },
                if p.z >= 0.0 { max.z } else { min.z },
            );
            p.truncate().dot(v) + p.w >= 0.0
        })
    }

    pub fn contains_point(&self, p: Vec3) -> bool {
        self.planes.iter().all(|pl| pl.truncate().dot(p) + pl.w >= 0.0)
    }
}

/// Distance from a point to an axis-aligned box (0 inside).
pub fn distance_to_aabb(p: Vec3, min: Vec3, max: Vec3) -> f32 {
    (min - p).max(p - max).max(Vec3::ZERO).length()
}

/// Pixels per world unit of a vertical deviation inside the box `[min, max]` for this
/// camera: `kappa cos(beta_b) / (cos^2(theta_b) * distance)`, see [`angular_factor`];
/// valid for deviations that are then checked against `delta` pixels.
pub fn world_to_pixels(cam: &Camera, min: Vec3, max: Vec3, delta: f32) -> f32 {
    cam.kappa() * angular_factor(cam, min, max, delta) / distance_to_aabb(cam.position, min, max).max(cam.near)
}

/// What the camera's orientation does to a vertical deviation inside the box, on top of
/// `kappa / distance` (the GPU data): the projection magnifies by up to
/// `1 / cos^2(theta_b)` off the optical axis, and only the part of a vertical segment
/// across the ray shows, at most `cos(beta_b)` of it (SPEC section 3). The off-axis
/// angle is clamped to the frustum widened by `delta` pixels, which is sound for an error
/// then compared with `delta` ([`Camera::inv_cos2_aabb`]).
pub fn angular_factor(cam: &Camera, min: Vec3, max: Vec3, delta: f32) -> f32 {
    cam.inv_cos2_aabb(min, max, delta) * cam.vertical_factor_aabb(min, max)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Looking down, tilted north by less and less down to none: the screen's up stays
    /// north (it turned to south below about 2.6 degrees, an adversarial review found).
    #[test]
    fn the_view_does_not_turn_over_near_nadir() {
        for tilt_deg in [10.0f32, 3.0, 2.5, 1.0, 0.1, 0.0] {
            let t = tilt_deg.to_radians();
            let cam = Camera::look_at(Vec3::ZERO, Vec3::new(0.0, -t.cos(), -t.sin()), 60.0, 100, 100, 0.1);
            let (right, up) = cam.basis();
            assert!(up.z < -0.5 && right.x > 0.5, "tilt {tilt_deg}: up {up}, right {right}");
        }
    }

    /// The image and the culling frustum are the same pyramid: the frustum's edge
    /// directions project onto the image's edges, also far from the origin and looking
    /// nearly straight down (an auditor found background showing through at the frame's
    /// edge there: the view matrix was built from `position + forward`, which f32 rounds
    /// at 70 km, turning the image 3.5 pixels away from the frustum).
    #[test]
    fn the_frustum_edges_project_onto_the_image_edges() {
        for (pos, target) in [
            (Vec3::new(73807.7, 13059.59, 85856.61), Vec3::new(74081.35, 0.0, 85937.77)),
            (Vec3::new(1.5e5, 900.0, 2.0e5), Vec3::new(1.6e5, 0.0, 1.9e5)),
            (Vec3::new(10.0, 5.0, -3.0), Vec3::new(40.0, 0.0, 7.0)),
        ] {
            let cam = Camera::look_at(pos, target, 20.0, 640, 480, 1.0);
            let (right, up) = cam.basis();
            let tv = (cam.fovy * 0.5).tan();
            let th = tv * cam.aspect();
            let vp = cam.view_proj();
            let at = |d: Vec3| cam.project(&vp, cam.position + d * 1000.0).unwrap();
            for (d, want) in [
                (cam.forward - th * right, (0.0, 240.0)),
                (cam.forward + th * right, (640.0, 240.0)),
                (cam.forward + tv * up, (320.0, 0.0)),
                (cam.forward - tv * up, (320.0, 480.0)),
            ] {
                let got = at(d);
                assert!(
                    (got.0 - want.0).abs() < 0.1 && (got.1 - want.1).abs() < 0.1,
                    "camera at {pos}: frustum edge projects to {got:?}, not {want:?}"
                );
            }
        }
    }

    /// A widened frustum holds the points that project up to its margin beyond the
    /// image's edges and no farther; the plain one stops at the edges.
    #[test]
    fn the_widened_frustum_reaches_its_margin_beyond_the_image() {
        let cam = Camera::look_at(Vec3::new(10.0, 5.0, -3.0), Vec3::new(40.0, 0.0, 7.0), 35.0, 640, 360, 0.1);
        let (right, up) = cam.basis();
        let tv = (cam.fovy * 0.5).tan();
        let th = tv * cam.aspect();
        let vp = cam.view_proj();
        // The point 100 units ahead that projects to pixel (px, py).
        let at = |px: f32, py: f32| {
            let d = cam.forward + (2.0 * px / 640.0 - 1.0) * th * right + (1.0 - 2.0 * py / 360.0) * tv * up;
            let p = cam.position + d * 100.0;
            let (gx, gy) = cam.project(&vp, p).unwrap();
            assert!((gx - px).abs() < 1e-2 && (gy - py).abs() < 1e-2, "({px}, {py}) projects to ({gx}, {gy})");
            p
        };
        let (plain, wide) = (cam.frustum(), cam.frustum_widened(2.0));
        for (px, py) in [(-1.9, 100.0), (641.9, 50.0), (300.0, -1.9), (10.0, 361.9)] {
            assert!(wide.contains_point(at(px, py)), "({px}, {py}) is inside the 2 px margin");
            assert!(!plain.contains_point(at(px, py)), "({px}, {py}) is outside the image");
        }
        for (px, py) in [(-2.1, 100.0), (642.1, 50.0), (300.0, -2.1), (10.0, 362.1)] {
            assert!(!wide.contains_point(at(px, py)), "({px}, {py}) is beyond the 2 px margin");
        }
        for (px, py) in [(0.1, 100.0), (639.9, 50.0), (300.0, 0.1), (10.0, 359.9)] {
            assert!(plain.contains_point(at(px, py)), "({px}, {py}) is inside the image");
        }
    }

    #[test]
    fn vertical_factor_bounds_the_foreshortening_of_every_ray_into_the_box() {
        let cam = Camera::look_at(Vec3::new(0.0, 50.0, 0.0), Vec3::new(0.0, 0.0, -10.0), 60.0, 640, 480, 0.5);
        // Straight below: a vertical deviation is seen end-on.
        assert!(cam.vertical_factor_aabb(Vec3::new(-0.1, 0.0, -0.1), Vec3::new(0.1, 1.0, 0.1)) < 0.01);
        // A box level with the eye: no saving.
        assert_eq!(cam.vertical_factor_aabb(Vec3::new(5.0, 40.0, 5.0), Vec3::new(6.0, 60.0, 6.0)), 1.0);
        let (lo, hi) = (Vec3::new(-30.0, 0.0, -80.0), Vec3::new(10.0, 12.0, -20.0));
        let f = cam.vertical_factor_aabb(lo, hi);
        assert!(f < 1.0);
        for t in 0..2000u32 {
            let r = |k: u32| ((t * 7919 + k * 104729) % 1000) as f32 / 1000.0;
            let q = lo + (hi - lo) * Vec3::new(r(1), r(2), r(3));
            let w = (q - cam.position).normalize();
            let cos_beta = (1.0 - w.y * w.y).sqrt();
            assert!(cos_beta <= f * (1.0 + 1e-5), "{cos_beta} > {f}");
        }
    }

    #[test]
    fn off_axis_factor_is_one_on_axis_and_the_corner_value_at_most() {
        let cam = Camera::look_at(Vec3::ZERO, Vec3::new(0.0, 0.0, -1.0), 60.0, 640, 480, 0.5);
        let on_axis = cam.inv_cos2_aabb(Vec3::new(-0.01, -0.01, -100.0), Vec3::new(0.01, 0.01, -99.0), 0.0);
        assert!((on_axis - 1.0).abs() < 1e-4, "{on_axis}");
        // A point to the right at tan = 0.5: 1/cos^2 = 1.25.
        let side = cam.inv_cos2_aabb(Vec3::new(5.0, 0.0, -10.0), Vec3::new(5.0, 0.0, -10.0), 0.0);
        assert!((side - 1.25).abs() < 1e-4, "{side}");
        // Wider than the frustum, or reaching behind the eye: the corner value.
        let corner = cam.inv_cos2_max();
        let wide = cam.inv_cos2_aabb(Vec3::new(100.0, -100.0, -1.0), Vec3::new(101.0, 100.0, -0.5), 0.0);
        assert!((wide - corner).abs() < 1e-5, "{wide} vs {corner}");
        assert!((cam.inv_cos2_aabb(Vec3::new(-1.0, -1.0, -1.0), Vec3::new(1.0, 1.0, 1.0), 0.0) - corner).abs() < 1e-5);
        // Far to the right but level with the eye: only the horizontal tangent is clamped.
        let th = (cam.fovy * 0.5).tan() * cam.aspect();
        let right = cam.inv_cos2_aabb(Vec3::new(100.0, -0.01, -1.0), Vec3::new(101.0, 0.01, -0.5), 0.0);
        assert!((right - (1.0 + th * th)).abs() < 1e-3, "{right}");
        // Every point inside the frustum has its own factor below the box's.
        let b = (Vec3::new(-3.0, -2.0, -9.0), Vec3::new(2.0, 1.0, -4.0));
        let f = cam.inv_cos2_aabb(b.0, b.1, 0.0);
        // A margin widens the clamp: a box far off to the side gets a larger factor.
        let wide = Vec3::new(100.0, -0.01, -1.0);
        assert!(
            cam.inv_cos2_aabb(wide, wide + Vec3::splat(0.5), 50.0)
                > cam.inv_cos2_aabb(wide, wide + Vec3::splat(0.5), 0.0)
        );
        for t in 0..1000 {
            let r = |k: u32| ((t * 7919 + k * 104729) % 1000) as f32 / 1000.0;
            let p = b.0 + (b.1 - b.0) * Vec3::new(r(1), r(2), r(3));
            let c = p.normalize().dot(cam.forward);
            assert!(1.0 / (c * c) <= f * (1.0 + 1e-5));
        }
    }

    #[test]
    fn projection_centre_and_frustum_agree() {
        let cam = Camera::look_at(Vec3::new(0.0, 10.0, 0.0), Vec3::new(0.0, 10.0, -100.0), 60.0, 640, 480, 0.5);
        let vp = cam.view_proj();
        let (x, y) = cam.project(&vp, Vec3::new(0.0, 10.0, -50.0)).unwrap();
        assert!((x - 320.0).abs() < 1e-3 && (y - 240.0).abs() < 1e-3);
        // A point above the centre appears above (smaller y).
        let (_, y2) = cam.project(&vp, Vec3::new(0.0, 15.0, -50.0)).unwrap();
        assert!(y2 < 240.0);
        let fr = cam.frustum();
        assert!(fr.contains_point(Vec3::new(0.0, 10.0, -50.0)));
        assert!(!fr.contains_point(Vec3::new(0.0, 10.0, 50.0)));
        assert!(!fr.intersects_aabb(Vec3::new(100.0, 0.0, -10.0), Vec3::new(120.0, 5.0, -5.0)));
        assert!(fr.intersects_aabb(Vec3::new(-1.0, 0.0, -60.0), Vec3::new(1.0, 20.0, -40.0)));
        // Points just inside the image edges are inside the frustum, and vice versa.
        for &(px, py) in &[(1.0f32, 1.0f32), (639.0, 479.0), (1.0, 479.0)] {
            let (r, u) = cam.basis();
            let t = (cam.fovy * 0.5).tan();
            let dir =
                cam.forward + r * ((px / 640.0) * 2.0 - 1.0) * t * cam.aspect() - u * ((py / 480.0) * 2.0 - 1.0) * t;
            let p = cam.position + dir * 30.0;
            assert!(fr.contains_point(p));
            let (qx, qy) = cam.project(&vp, p).unwrap();
            assert!((qx - px).abs() < 1e-2 && (qy - py).abs() < 1e-2, "{qx},{qy} vs {px},{py}");
        }
    }
}
