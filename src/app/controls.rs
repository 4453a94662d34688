//! The camera controls both viewers share: WASD/QE flight, walking on the ground, orbit,
//! drag to look and the wheel's speed, over any terrain that can say how high its ground
//! is ([`Ground`]: a heightfield in memory, or the tiles a streamed viewer holds).

use crate::lod::heightfield::Heightfield;
use crate::lod::view::near_plane_for;
use glam::Vec3;
use std::collections::HashSet;
use winit::event::{ElementState, MouseButton, MouseScrollDelta, WindowEvent};
use winit::keyboard::{KeyCode, PhysicalKey};

/// What the controls need of a terrain: its world extent from the origin, the ground's
/// height (world units) at a world `(x, z)` inside it, and its smaller sample spacing.
pub trait Ground {
    fn extent(&self) -> (f32, f32);
    fn height(&self, x: f32, z: f32) -> f32;
    fn spacing(&self) -> f32;
}

/// The first point of the ground along the ray from `from` in direction `dir` (marched
/// in steps over twice the terrain's extent), or a point on the ground a quarter of the
/// extent ahead when the ray meets none.
pub fn ground_hit(ground: &dyn Ground, from: Vec3, dir: Vec3) -> Vec3 {
    let (wx, wz) = ground.extent();
    let l = wx.max(wz);
    let height = |p: Vec3| ground.height(p.x.clamp(0.0, wx), p.z.clamp(0.0, wz));
    let steps = (2.0 * l / ground.spacing()).min(20_000.0) as usize;
    for i in 1..=steps {
        let p = from + dir * (i as f32 * 2.0 * l / steps as f32);
        if p.y <= height(p) && (0.0..=wx).contains(&p.x) && (0.0..=wz).contains(&p.z) {
            return p;
        }
    }
    let p = from + dir * 0.25 * l;
    Vec3::new(p.x, height(p), p.z)
}

impl Ground for Heightfield {
    fn extent(&self) -> (f32, f32) {
        self.world_extent()
    }
    fn height(&self, x: f32, z: f32) -> f32 {
        self.surface_height(x, z)
    }
    fn spacing(&self) -> f32 {
        self.spacing.min()
    }
}

/// Camera state driven by input or a flyover path.
pub struct Controller {
    pub position: Vec3,
    pub yaw: f32,
    pub pitch: f32,
    pub speed: f32,
    pub walk: bool,
    pub held: HashSet<KeyCode>,
    pub looking: bool,
    /// Orbit mode (O): the point looked at and the distance to it; dragging turns the
    /// camera around it, W/S move in and out.
    pub orbit: Option<(Vec3, f32)>,
}

impl Controller {
    /// At `position` looking along `forward` (unit), moving at `speed` world units a
    /// second, walking or flying.
    pub fn new(position: Vec3, forward: Vec3, speed: f32, walk: bool) -> Self {
        Controller {
            position,
            yaw: forward.z.atan2(forward.x),
            pitch: forward.y.clamp(-1.0, 1.0).asin(),
            speed,
            walk,
            held: HashSet::new(),
            looking: false,
            orbit: None,
        }
    }

    pub fn forward(&self) -> Vec3 {
        Vec3::new(self.yaw.cos() * self.pitch.cos(), self.pitch.sin(), self.yaw.sin() * self.pitch.cos())
    }

    /// O: orbit around the ground point along `ray` (the cursor's), turning to face it,
    /// or stop orbiting. Returns how far the camera turned to face it (radians).
    pub fn toggle_orbit(&mut self, ground: &dyn Ground, ray: Vec3) -> f32 {
        if self.orbit.take().is_some() {
            return 0.0;
        }
        let pivot = ground_hit(ground, self.position, ray);
        let to = pivot - self.position;
        let mut turned = 0.0;
        if to.length() > 0.0 {
            let d = to.normalize();
            let yaw = d.z.atan2(d.x);
            turned = (yaw - self.yaw).abs();
            (self.yaw, self.pitch) = (yaw, d.y.clamp(-1.0, 1.0).asin());
        }
        self.walk = false;
        self.orbit = Some((pivot, to.length().max(ground.spacing())));
        turned
    }

    /// The ray through the window pixel `cursor` (ahead when there is none or the window
    /// is empty), for a camera of vertical field of view `fovy_deg` in a window of `size`.
    pub fn cursor_ray(&self, cursor: Option<(f32, f32)>, size: (u32, u32), fovy_deg: f32) -> Vec3 {
        let fwd = self.forward();
        let (Some((x, y)), (w, h)) = (cursor, size) else { return fwd };
        if w == 0 || h == 0 {
            return fwd;
        }
        // The drawn camera's own basis, so that the ray meets what is under the cursor.
        let (right, up) = crate::lod::camera::Camera::look_at(Vec3::ZERO, fwd, 60.0, 1, 1, 1.0).basis();
        let t = (fovy_deg.to_radians() * 0.5).tan();
        let (nx, ny) = (2.0 * x / w as f32 - 1.0, 1.0 - 2.0 * y / h as f32);
        (fwd + right * (nx * t * w as f32 / h as f32) + up * (ny * t)).normalize()
    }

    pub fn update(&mut self, ground: &dyn Ground, dt: f32) {
        if let Some((pivot, radius)) = &mut self.orbit {
            let k = |c| self.held.contains(&c);
            let zoom = k(KeyCode::KeyS) as i32 - k(KeyCode::KeyW) as i32;
            *radius = (*radius * (1.0 + 1.5 * dt * zoom as f32)).max(ground.spacing());
            let (pivot, radius) = (*pivot, *radius);
            self.position = pivot - self.forward() * radius;
            self.clamp_to_ground(ground);
            return;
        }
        let fwd = self.forward();
        let flat = Vec3::new(fwd.x, 0.0, fwd.z).normalize_or_zero();
        let right = flat.cross(Vec3::Y);
        let mut v = Vec3::ZERO;
        let k = |c| self.held.contains(&c);
        if k(KeyCode::KeyW) {
            v += if self.walk { flat } else { fwd };
        }
        if k(KeyCode::KeyS) {
            v -= if self.walk { flat } else { fwd };
        }
        if k(KeyCode::KeyD) {
            v += right;
        }
        if k(KeyCode::KeyA) {
            v -= right;
        }
        if k(KeyCode::KeyE) {
            v += Vec3::Y;
        }
        if k(KeyCode::KeyQ) {
            v -= Vec3::Y;
        }
        let boost = if k(KeyCode::ShiftLeft) || k(KeyCode::ShiftRight) { 5.0 } else { 1.0 };
        self.position += v.normalize_or_zero() * self.speed * boost * dt;
        self.clamp_to_ground(ground);
    }

    /// Never below the terrain (seed 002); in walk mode, on the terrain at eye height
    /// (walking off an edge, or switching to walk outside, lands on its border).
    /// The viewers' `--flyover` at `t` in [0, 1): north from the south edge to three
    /// quarters of the way across (so the view ends on terrain), above the highest
    /// ground `top` by a twentieth of the terrain's size, looking ahead and down; kept
    /// above the ground under it.
    pub fn fly_over(&mut self, terrain: &dyn Ground, top: f32, t: f32) {
        let (wx, wz) = terrain.extent();
        self.position = Vec3::new(wx * 0.5, top + 0.05 * wx.max(wz), wz * (1.0 - 0.75 * t));
        self.yaw = -std::f32::consts::FRAC_PI_2;
        self.pitch = -0.35;
        self.clamp_to_ground(terrain);
    }

    pub fn clamp_to_ground(&mut self, terrain: &dyn Ground) {
        let (wx, wz) = terrain.extent();
        let ground = terrain.height(self.position.x.clamp(0.0, wx), self.position.z.clamp(0.0, wz));
        let eye = (2.0f32).max(near_plane_for(terrain.spacing()) * 4.0);
        if self.walk {
            self.position.x = self.position.x.clamp(0.0, wx);
            self.position.z = self.position.z.clamp(0.0, wz);
            self.position.y = ground + eye;
        } else {
            self.position.y = self.position.y.max(ground + eye);
        }
    }

    /// Drag to look: the cursor moved by `(dx, dy)` pixels turns the camera. Returns the
    /// yaw turned (radians).
    pub fn drag(&mut self, dx: f32, dy: f32) -> f32 {
        self.yaw += dx * 0.003;
        self.pitch = (self.pitch - dy * 0.003).clamp(-1.55, 1.55);
        (dx * 0.003).abs()
    }

    /// The wheel changes the speed by a quarter a notch.
    pub fn wheel(&mut self, delta: MouseScrollDelta) {
        let steps = match delta {
            MouseScrollDelta::LineDelta(_, y) => y,
            MouseScrollDelta::PixelDelta(p) => (p.y / 40.0) as f32,
        };
        self.speed *= 1.25f32.powf(steps);
    }
}

/// What a window event did to the controls ([`Controller::on_event`]).
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Input {
    /// A key was pressed (not a repeat): the viewer's own keys act on it.
    Pressed(KeyCode),
    /// Dragging turned the camera by this much yaw (radians).
    Turned(f32),
    /// The controls took the event (keys held, buttons, wheel, the cursor).
    Taken,
    /// Not an event of the controls.
    Other,
}

impl Controller {
    /// The events both viewers treat alike: keys held (W/S, A/D, Q/E, Shift), drag to look
    /// with either mouse button, the wheel's speed. `cursor`: the cursor's last position
    /// in the window, kept here.
    pub fn on_event(&mut self, event: &WindowEvent, cursor: &mut Option<(f32, f32)>) -> Input {
        match event {
            WindowEvent::KeyboardInput { event, .. } => {
                let PhysicalKey::Code(code) = event.physical_key else { return Input::Taken };
                if event.state == ElementState::Pressed {
                    self.held.insert(code);
                    if !event.repeat {
                        return Input::Pressed(code);
                    }
                } else {
                    self.held.remove(&code);
                }
                Input::Taken
            }
            WindowEvent::MouseInput { state, button: MouseButton::Left | MouseButton::Right, .. } => {
                self.looking = *state == ElementState::Pressed;
                Input::Taken
            }
            WindowEvent::CursorMoved { position, .. } => {
                // Drag to look: the cursor's motion inside the window turns the camera.
                let at = (position.x as f32, position.y as f32);
                let last = cursor.replace(at);
                match (self.looking, last) {
                    (true, Some(last)) => Input::Turned(self.drag(at.0 - last.0, at.1 - last.1)),
                    _ => Input::Taken,
                }
            }
            WindowEvent::CursorLeft { .. } => {
                *cursor = None;
                Input::Taken
            }
            WindowEvent::MouseWheel { delta, .. } => {
                self.wheel(*delta);
                Input::Taken
            }
            _ => Input::Other,
        }
    }
}

/// Delta after a key: `]`, `=` or keypad `+` double it, `[`, `-` or keypad `-` halve it
/// (at least 1/16 pixel); `None` for other keys.
pub fn delta_key(code: KeyCode, delta: f32) -> Option<f32> {
    match code {
        KeyCode::BracketRight | KeyCode::Equal | KeyCode::NumpadAdd => Some(delta * 2.0),
        KeyCode::BracketLeft | KeyCode::Minus | KeyCode::NumpadSubtract => Some((delta * 0.5).max(0.0625)),
        _ => None,
    }
}

/// A window titled `title` at `--size` (1280 x 720 by default), and the instance
/// (validation as asked), surface and device that draw into it: the device, its queue
/// mode and its notes printed; each of `sizes` (an option and the size it asks for)
/// checked against the device's maxImageDimension2D (exit 2). One copy for both viewers.
pub(crate) fn open_window(
    event_loop: &winit::event_loop::ActiveEventLoop,
    common: &crate::app::cli::CommonArgs,
    title: String,
    sizes: &[(String, u32, u32)],
) -> anyhow::Result<(std::sync::Arc<winit::window::Window>, crate::vk::Surface, std::sync::Arc<crate::vk::Device>)> {
    use crate::vk::{Device, DeviceOptions, Instance, InstanceOptions, Surface, VkResultExt};
    use raw_window_handle::{HasDisplayHandle, HasWindowHandle};
    let (w, h) = common.view.frustum.size.unwrap_or((1280, 720));
    let attrs = winit::window::Window::default_attributes()
        .with_title(title)
        .with_inner_size(winit::dpi::PhysicalSize::new(w, h));
    let window = std::sync::Arc::new(event_loop.create_window(attrs)?);
    let display = window.display_handle()?.as_raw();
    let exts: Vec<&'static std::ffi::CStr> = ash_window::enumerate_required_extensions(display)
        .vk("enumerate surface extensions")?
        .iter()
        // SAFETY: ash-window returns pointers to static NUL-terminated extension names.
        .map(|&p| unsafe { std::ffi::CStr::from_ptr(p) })
        .collect();
    let instance = Instance::new(&InstanceOptions { validation: common.device.validation(), extensions: exts })?;
    // SAFETY: the window outlives the surface: each viewer drops its GPU state (holding
    // the surface) before its window.
    let surface = unsafe { Surface::new(&instance, display, window.window_handle()?.as_raw())? };
    let device = Device::new(
        instance,
        &DeviceOptions { gpu: common.device.gpu.clone(), queues: common.device.queues, swapchain: true },
    )
    .map_err(crate::app::cli::option_error)?;
    eprintln!("vkterrain: device {}, queue mode {}", device.name, device.queue_mode.as_str());
    for note in device.notes() {
        eprintln!("vkterrain: note: {note}");
    }
    for (opt, w, h) in sizes {
        crate::app::cli::check_image_size(&device, opt, (*w, *h))?;
    }
    Ok((window, surface, device))
}

/// Where the `--flyover` is at frame `frame`: over the run with `--frames N`, else once
/// every 60 seconds since `started`.
pub fn flyover_time(frames: Option<u64>, frame: u64, started: std::time::Instant) -> f32 {
    match frames {
        Some(n) => frame as f32 / n.max(1) as f32,
        None => (started.elapsed().as_secs_f32() / 60.0).fract(),
    }
}
