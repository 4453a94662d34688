//! The viewer over an archive drawn streamed (SPEC section 8): a terrain of any size in a
//! window. The IO thread reads the tiles the view needs into the host cache while the
//! camera moves; each frame selects over what is held (blocks that should split but whose
//! tile has not arrived are drawn as they are and the frame is counted over the bound),
//! uploads the new tiles into the atlas and draws from it into the swapchain image.
//!
//! It has the in-memory viewer's camera controls ([`Controller`]), keys and panel
//! ([`crate::app::hud`], with its tiles section: frames over the bound, tiles held and
//! read, the errors over the atlas);
//! the window title carries the main figures too.

use crate::app::cli::{check_messages, CommonArgs, Degraded, Interrupted};
use crate::app::controls::{delta_key, flyover_time, ground_hit, Controller, Ground};
use crate::app::hud::{Controls, Hud, Legend, Place, Ranges, Readout, TilesReadout};
use crate::app::outputs::save_png;
use crate::app::stream::{top_tiles, GpuFrames};
use crate::app::window_loop::{WindowApp, WindowState, Windowed};
use crate::draw::streamed::WindowImage;
use crate::input::archive::Archive;
use crate::lod::view::near_plane_for;
use crate::stream::streamer::Streamer;
use crate::stream::traverse::View;
use crate::stream::Grid;
use crate::trace::{Trace, DRAW_TID};
use crate::vk::{vk, BinarySemaphore, Surface, Swapchain, VkResultExt};
use glam::Vec3;
use std::sync::Arc;
use std::time::{Duration, Instant};
use winit::event_loop::{ActiveEventLoop, ControlFlow, EventLoop};
use winit::keyboard::KeyCode;

/// The ground under the camera, from the tiles held (nearest vertex of the finest);
/// 0 where none is held yet.
struct HeldGround<'a>(&'a Streamer);

impl Ground for HeldGround<'_> {
    fn extent(&self) -> (f32, f32) {
        let [wx, wz] = self.0.grid.world_extent();
        (wx as f32, wz as f32)
    }
    fn height(&self, x: f32, z: f32) -> f32 {
        self.0.ground(f64::from(x), f64::from(z)).unwrap_or(0.0) as f32
    }
    fn spacing(&self) -> f32 {
        self.0.grid.spacing[0].min(self.0.grid.spacing[1]) as f32
    }
}

/// What the streamed viewer is asked to do (the viewer's options it takes).
#[derive(Clone, Debug)]
pub struct StreamViewOptions {
    pub common: CommonArgs,
    pub textures: crate::app::cli::TextureArgs,
    pub fog: Option<f32>,
    pub present: vk::PresentModeKHR,
    pub frames: Option<u64>,
    pub screenshot: Option<std::path::PathBuf>,
    pub frame_counter: Option<std::path::PathBuf>,
    pub walk: bool,
    pub cache_mb: u32,
    pub gpu_mb: u32,
    /// Start with the panel hidden (H shows it).
    pub no_hud: bool,
    /// The in-memory viewer's `--flyover` (the tiles read as it goes).
    pub flyover: bool,
    /// Start over this latitude and longitude (degrees), as the in-memory `--go-to`.
    pub go_to: Option<[f64; 2]>,
    /// Write every frame's camera position and look-at point here at exit (the poses
    /// `bench --path` replays).
    pub record_path: Option<std::path::PathBuf>,
    /// Heights drawn this many times the archive's scale (Z / X and the panel change it).
    pub exaggeration: f32,
    /// Window resizes asked at frames (frame, width, height).
    pub resizes: Vec<(u64, u32, u32)>,
    /// Write a Chrome trace here: the draw thread's frames, the IO thread's reads, the
    /// atlas's uploads.
    pub trace: Option<std::path::PathBuf>,
}

/// Everything that lives while the window is open, in drop order.
struct WindowGpu {
    hud: Hud,
    acquired: BinarySemaphore,
    swapchain: Swapchain,
    frames: GpuFrames,
    surface: Surface,
}

struct App {
    args: StreamViewOptions,
    /// Where the terrain is on the map (georeferenced terrains only).
    geo: Option<crate::app::geo::Geo>,
    /// `--texture` and `--detail`, read at start (a bad file fails before the window).
    textures: crate::app::cli::Textures,
    streamer: Streamer,
    grid: Grid,
    range: crate::draw::streamed::HeightRange,
    near: f32,
    fog: f32,
    ctl: Controller,
    home: (Vec3, f32, f32),
    delta: f32,
    /// Vertical exaggeration over the archive's (or `--height-scale`'s) scale.
    exaggeration: f32,
    /// The sun asked for (the panel); the lighting map follows when no slider is held.
    sun: Option<crate::draw::lighting::Sun>,
    /// Horizontal speed over the last frame (world units per second), for the panel.
    ground_speed: f32,
    true_height_scale: f64,
    /// Every frame's camera and look-at point, with `--record-path`.
    flight: Vec<(Vec3, Vec3)>,
    /// The window, what the event loop keeps of it, and the scripted run's options.
    win: WindowState,
    gpu: Option<WindowGpu>,
    last_frame: Instant,
    /// When the last frame was drawn (the panel's frame-time plot).
    last_drawn: Option<Instant>,
    started: Instant,
    title_at: Instant,
    fps_frames: u64,
    screenshots_asked: u64,
    /// The selection Space froze: drawn as the camera moves on (Space again thaws it).
    frozen: Option<crate::stream::traverse::Selection>,
    /// Space was pressed: the next frame's selection is frozen.
    freeze_next: bool,
    trace: Trace,
    run: crate::app::outputs::ViewerReport,
}

/// The viewer's start (and Home) view over a terrain known by its extent and heights: as
/// the in-memory viewer's, over its south part above its highest point, looking north.
fn start_view(grid: &Grid, [lo, hi]: [f32; 2]) -> (Vec3, Vec3) {
    let [wx, wz] = grid.world_extent().map(|e| e as f32);
    let l = wx.max(wz);
    (Vec3::new(wx * 0.5, hi + 0.08 * l, wz * 0.92), Vec3::new(wx * 0.5, lo, wz * 0.35))
}

/// Where the camera goes for a latitude and longitude (`--go-to`, the panel's go-to), as
/// the in-memory viewer's: `from` moved over it, as high above the ground there as it is
/// above the ground under it (at least a fiftieth of the terrain's size), the ground
/// from the tiles held.
fn go_to(geo: &crate::app::geo::Geo, streamer: &Streamer, from: Vec3, lat: f64, lon: f64) -> Result<Vec3, String> {
    let ground = HeldGround(streamer);
    let (wx, wz) = ground.extent();
    let (x, z) = geo.world_on_terrain(lat, lon, (wx, wz))?;
    let at = |x: f32, z: f32| ground.height(x.clamp(0.0, wx), z.clamp(0.0, wz));
    let above = (from.y - at(from.x, from.z)).max(0.02 * wx.max(wz));
    Ok(Vec3::new(x, at(x, z) + above, z))
}

/// `vkterrain view` over an archive drawn streamed.
pub fn view_streamed(args: &StreamViewOptions, archive: Arc<Archive>) -> anyhow::Result<()> {
    let shown = args.common.terrain.name();
    let mut grid = crate::app::stream::streamed_grid(&archive, &args.common.terrain.frame, args.common.block.k)?;
    let true_height_scale = grid.height_scale;
    // Only the drawn heights scale: the bound (`D * height_scale`) follows.
    grid.height_scale *= f64::from(args.exaggeration);
    let m = &archive.meta;
    eprintln!("{}", crate::app::stream::streamed_banner(&shown, m, args.cache_mb, args.gpu_mb));
    let textures = args.textures.load_over(&m.georef, (m.width, m.height))?;
    let trace = match &args.trace {
        Some(p) => {
            Trace::to_file(p).map_err(|e| crate::app::cli::InputError(format!("--trace {}: {e}", p.display())))?
        }
        None => Trace::off(),
    };
    // The device's own limit is known once the window is open; the atlas is cut to it.
    let layers = crate::errors::atlas::MAX_LAYERS;
    let mut streamer =
        crate::app::stream::atlas_bound_streamer(archive.clone(), grid, args.cache_mb, args.gpu_mb, layers, &trace)?;
    streamer.morph = crate::app::stream::morph_rule(args.common.lod.morph.setting);
    streamer.error_mode = args.common.error_mode.mode;
    streamer.refresh_at = args.common.refresh_at;
    let range = top_tiles(&mut streamer, &archive.meta)?;
    let near = near_plane_for(grid.spacing[0].min(grid.spacing[1]) as f32);
    let (position, target) =
        args.common.view.view_points(|| start_view(&grid, range.world)).map_err(anyhow::Error::from)?;
    let f = (target - position).normalize();
    let spacing = crate::lod::heightfield::Spacing { x: grid.spacing[0] as f32, z: grid.spacing[1] as f32 };
    let geo = crate::app::geo::Geo::new(&m.georef, spacing);
    let position = match (args.go_to, &geo) {
        (Some([lat, lon]), Some(geo)) => go_to(geo, &streamer, position, lat, lon)
            .map_err(|e| crate::app::cli::InputError(format!("--go-to {e}")))?,
        (Some(_), None) => {
            return Err(crate::app::cli::InputError(format!(
                "--go-to: {} says nothing about where it is (no CRS or geotransform)",
                m.source
            ))
            .into())
        }
        (None, _) => position,
    };
    // As `render` does: the first view's tiles are read before its first frame (in walk
    // mode, once the camera stands on the ground they bring).
    let (w, h) = args.common.view.frustum.size.unwrap_or((1280, 720));
    let mut position = position;
    for _ in 0..1 + usize::from(args.walk) {
        let first =
            View::look_at(position.as_dvec3(), (position + f).as_dvec3(), args.common.view.frustum.fovy, w, h, near);
        crate::app::stream::settle(&mut streamer, |_| first, args.common.lod.delta);
        if args.walk {
            let mut ctl = Controller::new(position, f, 0.0, true);
            ctl.clamp_to_ground(&HeldGround(&streamer));
            position = ctl.position;
        }
    }
    let [wx, wz] = grid.world_extent();
    let l = wx.max(wz) as f32;
    let stop = super::signals::Stop::install();
    let interrupted = stop.flag().clone();
    let event_loop = EventLoop::new().map_err(|e| {
        anyhow::anyhow!("cannot open a window ({e}); is DISPLAY set? Use `vkterrain render` for headless output")
    })?;
    event_loop.set_control_flow(ControlFlow::Poll);
    // The same table as the panel's key help (F1), as the in-memory viewer prints it.
    eprintln!("keys:");
    for (k, what) in crate::app::hud::KEYS {
        eprintln!("  {k:<13} {what}");
    }
    let ctl = Controller::new(position, f, l / 60.0, args.walk);
    let home = (ctl.position, ctl.yaw, ctl.pitch);
    let now = Instant::now();
    // The one block mesh's bytes, as the in-memory viewer reports them.
    let geometry_bytes = crate::app::commands::renderer_geometry_bytes(grid.block_quads as u32 + 1);
    let app = App {
        args: args.clone(),
        geo,
        textures,
        streamer,
        grid,
        range,
        near,
        fog: args.fog.unwrap_or(crate::lod::view::default_fog(l)),
        ctl,
        home,
        delta: args.common.lod.delta,
        exaggeration: args.exaggeration,
        sun: args.common.sun.0,
        ground_speed: 0.0,
        true_height_scale,
        flight: Vec::new(),
        win: WindowState::new(interrupted, args.frames, args.screenshot.clone(), args.resizes.clone()),
        gpu: None,
        last_frame: now,
        last_drawn: None,
        started: now,
        title_at: now,
        fps_frames: 0,
        screenshots_asked: 0,
        frozen: None,
        freeze_next: false,
        trace: trace.clone(),
        run: crate::app::outputs::ViewerReport {
            streamed: true,
            worst_factor: 1.0,
            camera: crate::app::outputs::ViewerCamera { start_position: position.to_array(), ..Default::default() },
            state: crate::app::outputs::ViewerState { exaggeration: args.exaggeration, ..Default::default() },
            geometry_bytes,
            terrain: crate::app::outputs::TerrainFacts::of_archive(&archive.meta, &args.common.terrain.frame),
            ..Default::default()
        },
    };
    let mut windowed = Windowed(app);
    event_loop.run_app(&mut windowed)?;
    let mut app = windowed.0;
    if let Some(e) = app.win.error.take() {
        return Err(e);
    }
    if let Some(path) = &args.record_path {
        crate::app::bench::record_poses(path, &app.flight)?;
    }
    let secs = app.started.elapsed().as_secs_f64();
    let mut run = std::mem::take(&mut app.run);
    run.seconds = secs;
    run.avg_fps = run.frames as f64 / secs.max(1e-9);
    run.camera.final_position = app.ctl.position.to_array();
    (run.camera.final_yaw, run.camera.final_pitch, run.state.final_delta) = (app.ctl.yaw, app.ctl.pitch, app.delta);
    (run.state.final_morph, run.state.frozen, run.camera.orbiting) =
        (app.streamer.morph.is_some(), app.frozen.is_some(), app.ctl.orbit.is_some());
    run.state.wireframe = app.gpu.as_ref().is_some_and(|g| g.frames.wireframe);
    run.state.final_error_mode = app.streamer.error_mode.as_str();
    run.state.final_sun = app.gpu.as_ref().and_then(|g| g.frames.lit_sun().0).map(|s| [s.azimuth, s.elevation]);
    // As the in-memory viewer's: the height scale drawn at exit (exaggerated).
    run.terrain.height_scale_m = app.grid.height_scale as f32;
    run.state.exaggeration = app.exaggeration;
    run.stream = Some(app.streamer.stats.clone());
    run.first_failure = app.streamer.first_failure.clone();
    run.degraded = run.first_failure.is_some();
    run.interrupted = stop.requested();
    let messages = app.gpu.as_ref().map(|g| g.frames.device.instance.messages.clone());
    if let Some(g) = &app.gpu {
        run.state.hud_visible = g.hud.visible;
        run.gpu = Some(g.frames.report());
        run.error_generations = g.frames.errors_shaded().generations;
        run.most_generations_in_flight = g.frames.errors_in_flight();
        let instance = &g.frames.device.instance;
        run.validation_messages = instance.validation.then(|| instance.validation_messages());
    }
    // Everything Vulkan goes before the messages are counted for the exit status (and the
    // IO thread is joined: its last read is in the trace).
    drop(app);
    if let Some(p) = &args.trace {
        trace.finish().map_err(|e| anyhow::anyhow!("{}: {e}", p.display()))?;
        eprintln!("vkterrain: trace {}", p.display());
    }
    crate::out!("{}", serde_json::to_string(&run)?)?;
    if let Some(m) = messages {
        check_messages(&m)?;
    }
    if stop.requested() {
        return Err(Interrupted::by(&stop, "the session's figures printed above").into());
    }
    if let Some(failure) = &run.first_failure {
        return Err(
            Degraded(format!("tiles could not be read (first: {failure}); frames drawn without their data")).into()
        );
    }
    Ok(())
}

impl App {
    fn open(&mut self, event_loop: &ActiveEventLoop) -> anyhow::Result<()> {
        let (w, h) = self.args.common.view.frustum.size.unwrap_or((1280, 720));
        let title = format!("vkterrain: {} (streamed)", self.args.common.terrain.name());
        let resizes = self.win.resizes.iter().map(|&(f, w, h)| (format!("--resize-at {f}"), w, h));
        let sizes: Vec<(String, u32, u32)> = std::iter::once(("--size".to_string(), w, h)).chain(resizes).collect();
        let (window, surface, device) =
            crate::app::controls::open_window(event_loop, &self.args.common, title, &sizes)?;
        let size = window.inner_size();
        let swapchain = Swapchain::new(&device, &surface, (size.width, size.height), self.args.present, None)?;
        self.run.device = device.name.clone();
        self.run.queue_mode = device.queue_mode.as_str().into();
        let acquired = BinarySemaphore::new(&device)?;
        // One frame in flight: each streamed frame is waited for before the next.
        let mut hud = Hud::new(&device, &window, swapchain.format, crate::draw::blocks::DEPTH_FORMAT, 1)?;
        hud.visible = !self.args.no_hud;
        let threads = self.args.common.lod.traversal_threads;
        crate::app::stream::streamer_threads(&mut self.streamer, threads, Some(&device))?;
        let mut frames = GpuFrames::new(device, &mut self.streamer, self.args.gpu_mb, self.range, (w, h), &self.trace)?;
        frames.pace_errors(&self.args.common);
        frames.fog = self.fog;
        frames.set_textures(&self.textures, &self.args.textures)?;
        frames.sun(self.args.common.sun.0)?;
        frames.occlusion = self.args.common.occlusion != Some(crate::app::cli::OnOff::Off);
        self.gpu = Some(WindowGpu { hud, acquired, swapchain, frames, surface });
        self.win.window = Some(window);
        Ok(())
    }

    fn recreate_swapchain(&mut self) -> anyhow::Result<()> {
        let (Some(gpu), Some(window)) = (self.gpu.as_mut(), self.win.window.as_ref()) else { return Ok(()) };
        let size = window.inner_size();
        if size.width == 0 || size.height == 0 {
            return Ok(());
        }
        gpu.frames.device.wait_idle()?;
        let mode = self.args.present;
        let new =
            Swapchain::new(&gpu.frames.device, &gpu.surface, (size.width, size.height), mode, Some(&gpu.swapchain))?;
        gpu.swapchain = new;
        gpu.hud.set_format(gpu.swapchain.format, crate::draw::blocks::DEPTH_FORMAT)?;
        self.win.swapchain_dirty = false;
        self.run.resizes += 1;
        Ok(())
    }

    /// The view the camera gives at `extent` (the swapchain's size).
    fn view(&self, width: u32, height: u32) -> View {
        let p = self.ctl.position.as_dvec3();
        View::look_at(
            p,
            p + self.ctl.forward().as_dvec3(),
            self.args.common.view.frustum.fovy,
            width,
            height,
            self.near,
        )
    }

    /// One frame ([`WindowApp::draw`]: the window is open and shown).
    fn draw_frame(&mut self) -> anyhow::Result<()> {
        if self.win.swapchain_dirty {
            self.recreate_swapchain()?;
        }
        let now = Instant::now();
        let dt = (now - self.last_frame).as_secs_f32().min(0.25);
        self.last_frame = now;
        let before = self.ctl.position;
        if self.args.flyover {
            let t = flyover_time(self.args.frames, self.run.frames, self.started);
            self.ctl.fly_over(&HeldGround(&self.streamer), self.range.world[1], t);
        } else {
            self.ctl.update(&HeldGround(&self.streamer), dt);
            if let Some((pivot, radius)) = self.ctl.orbit {
                let drift = ((self.ctl.position - pivot).length() - radius).abs() / radius;
                self.run.camera.orbit_drift = self.run.camera.orbit_drift.max(drift);
            }
        }
        let velocity = (self.ctl.position - before) / dt.max(1e-6);
        self.ground_speed = glam::Vec2::new(velocity.x, velocity.z).length();
        let Some(gpu) = self.gpu.as_ref() else { return Ok(()) };
        let extent = gpu.swapchain.extent;
        let view = self.view(extent.width, extent.height);
        if self.args.record_path.is_some() {
            self.flight.push((self.ctl.position, self.ctl.position + self.ctl.forward()));
        }
        // Where the camera will be in half a second: its tiles are asked for next.
        let ahead = View { position: view.position + velocity.as_dvec3() * 0.5, ..view };
        let selecting = Instant::now();
        let sel = self.streamer.frame(&view, Some(&ahead), self.delta, 0.5);
        if std::mem::take(&mut self.freeze_next) {
            self.frozen = Some(sel.clone());
        }
        let frame = serde_json::json!({"frame": self.run.frames});
        self.trace.complete(DRAW_TID, "select (traversal over held tiles)", selecting, Instant::now(), frame.clone());
        if !sel.within_bound() {
            self.run.frames_over_bound += 1;
            self.run.worst_factor = self.run.worst_factor.max(sel.worst_factor);
        }
        let interval = interval_ms(&mut self.last_drawn);
        self.panel(&sel, interval)?;
        let gpu = self.gpu.as_mut().expect("checked above");
        // SAFETY: the swapchain and semaphore are live; the last frame was waited for, so
        // the acquire semaphore is unsignalled and free.
        let acquire = unsafe {
            gpu.swapchain.loader.acquire_next_image(
                gpu.swapchain.handle,
                u64::MAX,
                gpu.acquired.handle,
                vk::Fence::null(),
            )
        };
        let (index, suboptimal) = match acquire {
            Ok(r) => r,
            Err(vk::Result::ERROR_OUT_OF_DATE_KHR) => {
                self.win.swapchain_dirty = true;
                return Ok(());
            }
            Err(e) => return Err(e).vk("vkAcquireNextImageKHR").map_err(Into::into),
        };
        let i = index as usize;
        let target = WindowImage {
            image: gpu.swapchain.images[i],
            view: gpu.swapchain.views[i],
            format: gpu.swapchain.format,
            extent,
            acquired: gpu.acquired.handle,
            done: gpu.swapchain.render_done[i],
        };
        let hud = &mut gpu.hud;
        let panel = hud.visible;
        let (mut hud_error, mut recorded) = (None, false);
        let mut draw_hud = |cmd| {
            recorded = true;
            if let Err(e) = hud.record(cmd, extent) {
                hud_error = Some(e);
            }
        };
        let overlay: Option<crate::draw::streamed::Overlay> = if panel { Some(&mut draw_hud) } else { None };
        let drawn = self.frozen.as_ref().unwrap_or(&sel);
        gpu.frames.draw(&self.streamer, &self.grid, &view, drawn, Some((&target, overlay)))?;
        if let Some(e) = hud_error {
            return Err(e);
        }
        // Counted where the panel was recorded into the frame, not where it was asked for.
        self.run.hud_frames += u64::from(recorded);
        let swapchains = [gpu.swapchain.handle];
        let indices = [index];
        let wait = [target.done];
        let present =
            vk::PresentInfoKHR::default().wait_semaphores(&wait).swapchains(&swapchains).image_indices(&indices);
        let presenting = Instant::now();
        let presented = {
            let _lock = gpu.frames.device.draw_queue.lock();
            // SAFETY: the queue is locked; the image was acquired and rendered.
            unsafe { gpu.swapchain.loader.queue_present(gpu.frames.device.draw_queue.handle, &present) }
        };
        match presented {
            Ok(sub) => self.win.swapchain_dirty |= sub || suboptimal,
            Err(vk::Result::ERROR_OUT_OF_DATE_KHR) => self.win.swapchain_dirty = true,
            Err(e) => return Err(e).vk("vkQueuePresentKHR").map_err(Into::into),
        }
        self.trace.complete(DRAW_TID, "present", presenting, Instant::now(), frame.clone());
        if let Some(path) = self.win.screenshot_next.take() {
            // The same frame again, offscreen at the window's size, read back.
            let (w, h) = (extent.width, extent.height);
            gpu.frames.resize(w, h)?;
            let drawn = self.frozen.as_ref().unwrap_or(&sel);
            gpu.frames.draw(&self.streamer, &self.grid, &view, drawn, None)?;
            save_png(&path, w, h, &gpu.frames.last)?;
            eprintln!("vkterrain: screenshot {}", path.display());
            self.run.screenshot = Some(path.display().to_string());
        }
        self.trace.complete(DRAW_TID, "frame", now, Instant::now(), frame);
        self.trace.counter("tiles held", self.streamer.cache.len() as u64);
        self.run.frames += 1;
        self.run.last_blocks = gpu.frames.drawn.blocks;
        self.run.last_triangles = gpu.frames.drawn.triangles;
        self.run.last_draw_calls = gpu.frames.drawn.draw_calls;
        self.fps_frames += 1;
        if let Some(path) = &self.args.frame_counter {
            let frames = self.run.frames.to_string();
            crate::app::outputs::write_atomic(path, |tmp| {
                std::fs::write(tmp, &frames).map_err(|e| anyhow::anyhow!("{}: {e}", path.display()))
            })?;
        }
        self.update_title();
        Ok(())
    }

    /// Builds this frame's panel from the last frame's figures and applies what its
    /// controls changed; `interval_ms`: the time since the last frame (the plots).
    fn panel(&mut self, sel: &crate::stream::traverse::Selection, interval_ms: Option<f32>) -> anyhow::Result<()> {
        let (Some(window), Some(gpu)) = (self.win.window.clone(), self.gpu.as_mut()) else { return Ok(()) };
        let p = self.ctl.position;
        let s = &self.streamer.stats;
        let report = gpu.frames.report();
        let [wx, wz] = self.grid.world_extent().map(|e| e as f32);
        let l = wx.max(wz);
        let errors = gpu.frames.errors_shaded();
        let tiles = TilesReadout {
            // This frame included, as in the count over the bound.
            frames: self.run.frames + 1,
            frames_over_bound: self.run.frames_over_bound,
            worst_factor: self.run.worst_factor,
            within_bound: sel.within_bound(),
            held: self.streamer.cache.len(),
            cache_mb: self.streamer.cache.bytes() as f64 / f64::from(1u32 << 20),
            cache_budget_mb: self.args.cache_mb,
            loaded: s.tiles_loaded,
            evicted: s.tiles_evicted,
            failed: s.tiles_failed,
            read_mb: s.bytes_read as f64 / f64::from(1u32 << 20),
            atlas_layers: report["atlas_layers"].as_u64().unwrap_or(0) as u32,
            uploaded: report["tiles_uploaded"].as_u64().unwrap_or(0),
            errors: errors.last,
            blocks_bounded_by_errors: sel.drawn_bounded_by().0,
        };
        let (lit_sun, lighting_ms) = gpu.frames.lit_sun();
        let mut readout = Readout {
            triangles: self.run.last_triangles,
            draw_calls: gpu.frames.drawn.draw_calls,
            occlusion: gpu.frames.last_occlusion.filter(|_| gpu.frames.occlusion),
            gpu_frame_ms: gpu.frames.drawn.gpu_ms,
            blocks: self.run.last_blocks,
            generations: errors.generations,
            update_ms: errors.last.and_then(|e| e.gpu_ms),
            // Over tiles the errors thread finishes each generation before the next.
            in_flight: (u64::from(errors.generations > 0), true),
            device: gpu.frames.device.name.clone(),
            queue_mode: gpu.frames.device.queue_mode.as_str().into(),
            camera_mode: if self.args.flyover {
                "flyover"
            } else if self.ctl.walk {
                "walk"
            } else if self.ctl.orbit.is_some() {
                "orbit"
            } else {
                "fly"
            },
            position: p,
            above_ground: p.y - HeldGround(&self.streamer).height(p.x, p.z),
            ground_speed: self.ground_speed,
            panel_ms: gpu.hud.last_ms,
            lighting_ms,
            lit_sun,
            wireframe_available: gpu.frames.device.features.wireframe,
            ranges: Ranges { fog_default: crate::lod::view::default_fog(l), speed: (l / 6000.0, l / 6.0) },
            legend: self
                .textures
                .base
                .is_none()
                .then_some(Legend { absolute: self.range.absolute, range_m: self.range.world }),
            tiles: Some(tiles),
            ..Readout::default()
        };
        if let Some(geo) = &self.geo {
            // One march along the cursor's ray a frame, for the panel and the exit figures.
            let ground = HeldGround(&self.streamer);
            let size = (window.inner_size().width, window.inner_size().height);
            let fovy = self.args.common.view.frustum.fovy;
            let ray = self.ctl.cursor_ray(self.win.cursor, size, fovy);
            let inside = |q: &Vec3| (0.0..=wx).contains(&q.x) && (0.0..=wz).contains(&q.z);
            let cursor = self.win.cursor.map(|_| ground_hit(&ground, p, ray)).filter(inside);
            let place = Place::of(geo, &self.ctl, &ground, cursor, (size.1, fovy), self.exaggeration);
            readout.place = Some(place);
            self.run.camera.camera_lat_lon = geo.lat_lon(p.x, p.z);
            self.run.camera.cursor_place = cursor.and_then(|q| {
                let [lat, lon] = geo.lat_lon(q.x, q.z)?;
                let ground_m = q.y / self.exaggeration;
                Some(serde_json::json!({ "lat": lat, "lon": lon, "ground_m": ground_m, "world": [q.x, q.y, q.z] }))
            });
        }
        if let Some(ms) = interval_ms {
            let t = gpu.hud.now();
            gpu.hud.history.push(t, ms);
        }
        let before = self.controls();
        let mut after = before;
        let gpu = self.gpu.as_mut().expect("checked above");
        gpu.hud.prepare(&window, &readout, &mut after)?;
        if after != before {
            self.apply(after)?;
        }
        // The lighting map is redrawn once the sun's sliders are let go.
        let gpu = self.gpu.as_mut().expect("checked above");
        if gpu.frames.lit_sun().0 != self.sun && !gpu.hud.pointer_busy() {
            gpu.frames.sun(self.sun)?;
        }
        Ok(())
    }

    /// The state the panel and the keys both change.
    fn controls(&self) -> Controls {
        let gpu = self.gpu.as_ref();
        Controls {
            delta: self.delta,
            mode: self.streamer.error_mode,
            morph: self.streamer.morph.is_some(),
            occlusion: gpu.is_some_and(|g| g.frames.occlusion),
            frozen: self.frozen.is_some() || self.freeze_next,
            wireframe: gpu.is_some_and(|g| g.frames.wireframe),
            colour_by_lod: gpu.is_some_and(|g| g.frames.colour_by_lod),
            deferred: gpu.is_some_and(|g| g.frames.deferred_asked()),
            fog_density: gpu.map_or(self.fog, |g| g.frames.fog),
            speed: self.ctl.speed,
            go_home: false,
            sun: self.sun,
            go_to: None,
            exaggeration: self.exaggeration,
        }
    }

    /// What the panel changed.
    fn apply(&mut self, c: Controls) -> anyhow::Result<()> {
        if c.frozen != (self.frozen.is_some() || self.freeze_next) {
            self.freeze_next = c.frozen;
            self.frozen = None;
        }
        self.delta = c.delta;
        self.streamer.error_mode = c.mode;
        self.set_morph(c.morph);
        if let Some(g) = self.gpu.as_mut() {
            g.frames.occlusion = c.occlusion;
            g.frames.wireframe = c.wireframe;
            g.frames.colour_by_lod = c.colour_by_lod;
            g.frames.fog = c.fog_density;
            use crate::draw::blocks::PixelPass;
            g.frames.set_pixels(if c.deferred { PixelPass::Deferred } else { PixelPass::Forward });
        }
        self.ctl.speed = c.speed;
        self.sun = c.sun;
        self.set_exaggeration(c.exaggeration)?;
        if c.go_home {
            self.go_home();
        }
        if let (Some([lat, lon]), Some(geo)) = (c.go_to, &self.geo) {
            // The camera stays where it is; the panel's box keeps what was typed.
            match go_to(geo, &self.streamer, self.ctl.position, lat, lon) {
                Ok(at) => (self.ctl.position, self.ctl.orbit) = (at, None),
                Err(e) => eprintln!("vkterrain: note: go-to {e}"),
            }
        }
        Ok(())
    }

    /// Geomorphing on or off from the next frame.
    fn set_morph(&mut self, on: bool) {
        if on != self.streamer.morph.is_some() {
            let setting = if on { crate::app::cli::OnOff::On } else { crate::app::cli::OnOff::Off };
            self.streamer.morph = crate::app::stream::morph_rule(setting);
        }
    }

    /// Draws heights `exaggeration` times the archive's scale from the next frame: the
    /// traversal's bound, the ground and the colours all follow the one scale (no errors
    /// to recompute: a tile's `D` is in raw units); the lighting map is redrawn.
    fn set_exaggeration(&mut self, exaggeration: f32) -> anyhow::Result<()> {
        if exaggeration == self.exaggeration {
            return Ok(());
        }
        let ratio = exaggeration / self.exaggeration;
        self.exaggeration = exaggeration;
        let scale = self.true_height_scale * f64::from(exaggeration);
        self.grid.height_scale = scale;
        self.streamer.grid.height_scale = scale;
        self.range.world = self.range.world.map(|h| h * ratio);
        if let Some(g) = self.gpu.as_mut() {
            g.frames.range = self.range;
            g.frames.set_height_scale(scale)?;
        }
        Ok(())
    }

    fn go_home(&mut self) {
        (self.ctl.position, self.ctl.yaw, self.ctl.pitch) = self.home;
        self.ctl.walk = false;
    }

    fn update_title(&mut self) {
        let elapsed = self.title_at.elapsed();
        if elapsed < Duration::from_millis(250) {
            return;
        }
        let fps = self.fps_frames as f64 / elapsed.as_secs_f64();
        self.title_at = Instant::now();
        self.fps_frames = 0;
        let p = self.ctl.position;
        let ground = HeldGround(&self.streamer).height(p.x, p.z);
        let s = &self.streamer.stats;
        let title = format!(
            "vkterrain (streamed) | {fps:.1} fps | {} blocks {} tris | delta {} | {} of {} frames over the bound | {} tiles held, {:.0} MB | {:.0} above ground{}",
            self.run.last_blocks,
            self.run.last_triangles,
            self.delta,
            self.run.frames_over_bound,
            self.run.frames,
            self.streamer.cache.len(),
            s.peak_cache_bytes as f64 / f64::from(1u32 << 20),
            p.y - ground,
            if self.ctl.walk { " | walk" } else { "" },
        );
        if let Some(w) = &self.win.window {
            w.set_title(&title);
        }
    }

    fn key(&mut self, code: KeyCode, event_loop: &ActiveEventLoop) {
        match code {
            KeyCode::Escape => event_loop.exit(),
            code if delta_key(code, self.delta).is_some() => {
                self.delta = delta_key(code, self.delta).unwrap_or(self.delta)
            }
            KeyCode::Home => self.go_home(),
            KeyCode::KeyL => {
                if let Some(g) = self.gpu.as_mut() {
                    g.frames.colour_by_lod = !g.frames.colour_by_lod;
                }
            }
            KeyCode::KeyX | KeyCode::KeyZ => {
                let e = crate::app::hud::exaggeration_key(code, self.exaggeration).unwrap_or(self.exaggeration);
                if let Err(e) = self.set_exaggeration(e) {
                    self.win.fail(event_loop, e);
                }
            }
            KeyCode::KeyH | KeyCode::F1 => {
                if let Some(g) = self.gpu.as_mut() {
                    g.hud.on_key(code);
                }
            }
            KeyCode::KeyG => {
                self.ctl.walk = !self.ctl.walk;
                self.ctl.clamp_to_ground(&HeldGround(&self.streamer));
            }
            KeyCode::KeyP => {
                self.screenshots_asked += 1;
                self.win.screenshot_next = Some(crate::app::outputs::next_free_screenshot());
            }
            KeyCode::KeyN => self.set_morph(self.streamer.morph.is_none()),
            KeyCode::KeyO => {
                // Around the ground point under the cursor (ahead when the cursor is
                // outside the window), from the tiles held.
                let size = self.win.window.as_ref().map_or((0, 0), |w| (w.inner_size().width, w.inner_size().height));
                let ray = self.ctl.cursor_ray(self.win.cursor, size, self.args.common.view.frustum.fovy);
                let turned = self.ctl.toggle_orbit(&HeldGround(&self.streamer), ray);
                if self.ctl.orbit.is_some() {
                    self.run.camera.orbit_aim_turn = turned;
                }
            }
            KeyCode::Space => {
                self.freeze_next = self.frozen.is_none();
                self.frozen = None;
            }
            KeyCode::KeyF => {
                if let Some(g) = self.gpu.as_mut() {
                    g.frames.wireframe = !g.frames.wireframe;
                    if !g.frames.device.features.wireframe {
                        eprintln!("vkterrain: note: this device has no wireframe (fillModeNonSolid)");
                    }
                }
            }
            KeyCode::KeyC => {
                if let Some(g) = self.gpu.as_mut() {
                    g.frames.occlusion = !g.frames.occlusion;
                }
            }
            KeyCode::KeyM => {
                use crate::lod::gie::ErrorMode;
                let m = &mut self.streamer.error_mode;
                *m = if *m == ErrorMode::Strict { ErrorMode::Paper } else { ErrorMode::Strict };
            }
            _ => {}
        }
    }
}

impl WindowApp for App {
    fn window_state(&mut self) -> &mut WindowState {
        &mut self.win
    }

    fn hud(&mut self) -> Option<&mut Hud> {
        self.gpu.as_mut().map(|g| &mut g.hud)
    }

    fn open(&mut self, event_loop: &ActiveEventLoop) -> anyhow::Result<()> {
        App::open(self, event_loop)
    }

    fn camera_controls(&mut self) -> (&mut Controller, &mut WindowState) {
        (&mut self.ctl, &mut self.win)
    }

    fn key(&mut self, code: KeyCode, event_loop: &ActiveEventLoop) {
        App::key(self, code, event_loop)
    }

    fn turned(&mut self, turned: f32) {
        self.run.camera.mouse_turn += turned;
        if self.ctl.orbit.is_some() {
            self.run.camera.orbit_turn += turned;
        }
    }

    fn frames_drawn(&self) -> u64 {
        self.run.frames
    }

    fn draw(&mut self) -> anyhow::Result<()> {
        self.draw_frame()
    }
}

impl Drop for App {
    fn drop(&mut self) {
        // Nothing may be destroyed while the GPU still uses it.
        if let Some(g) = &self.gpu {
            let _ = g.frames.device.wait_idle();
        }
        self.gpu = None;
    }
}

/// Milliseconds since `last` (None at the first frame), which becomes now.
fn interval_ms(last: &mut Option<Instant>) -> Option<f32> {
    let now = Instant::now();
    let ms = last.map(|t| (now - t).as_secs_f32() * 1e3);
    *last = Some(now);
    ms
}
