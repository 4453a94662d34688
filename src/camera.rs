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

    /// Camera basis (right, up) for the current forward.
    pub fn basis(&self) -> (Vec3, Vec3) {
        let world_up = if self.forward.y.abs() > 0.999 { Vec3::Z } else { Vec3::Y };
        let right = self.forward.cross(world_up).normalize();
        (right, right.cross(self.forward))
    }

    pub fn view(&self) -> Mat4 {
        let (_, up) = self.basis();
        Mat4::look_at_rh(self.position, self.position + self.forward, up)
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

    /// Pixel coordinates (x right, y down) of a world point, or `None` behind the eye.
    pub fn project(&self, view_proj: &Mat4, p: Vec3) -> Option<(f32, f32)> {
        let c = *view_proj * p.extend(1.0);
        if c.w <= 1e-12 {
            return None;
        }
        Some(((c.x / c.w * 0.5 + 0.5) * self.width as f32, (c.y / c.w * 0.5 + 0.5) * self.height as f32))
    }

    pub fn frustum(&self) -> Frustum {
        let (right, up) = self.basis();
        let tv = (self.fovy * 0.5).tan();
        let th = tv * self.aspect();
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

#[cfg(test)]
mod tests {
    use super::*;

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
