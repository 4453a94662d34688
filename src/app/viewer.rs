//! The desktop viewer: a winit window whose event-loop thread is the blocks rendering
//! activity (traversal and drawing on the draw queue), with the errors activity live on
//! its own thread and queue.

use crate::app::cli::{CommonArgs, InputError, Interrupted, TextureArgs, Textures};
use crate::app::commands::Session;
use crate::app::controls::{delta_key, flyover_time, ground_hit, Controller};
use crate::app::hud::{Controls, Hud, Ranges, Readout};
use crate::app::outputs::save_png;
use crate::app::window_loop::{WindowApp, WindowState, Windowed};
use crate::draw::blocks::{BlocksRenderer, DrawStats, FrameDest, FrameSync, PixelPass, Shading, DEPTH_FORMAT};
use crate::draw::frame::{traversal_threads, DrawThread, FrameRequest, LodChoice, LodTerrain};
use crate::draw::lighting::Sun;
use crate::errors::activity::ErrorsActivity;
use crate::gpu::terrain::{TerrainGpu, Texture};
use crate::lod::block::{BlockLayout, DrawBlock};
use crate::lod::camera::Camera;
use crate::lod::gie::ErrorMode;
use crate::lod::heightfield::Heightfield;
use crate::lod::pyramid::MinMaxPyramid;
use crate::lod::view::near_plane;
use crate::trace::{Trace, DRAW_TID};
use crate::vk::{
    vk, BinarySemaphore, Buffer, Device, DeviceOptions, Image, Instance, InstanceOptions, Surface, Swapchain,
    VkResultExt,
};
use clap::{Args, ValueEnum};
use glam::Vec3;
use serde_json::json;
use std::path::PathBuf;
use std::sync::Arc;
use std::time::{Duration, Instant};
use winit::event_loop::{ActiveEventLoop, ControlFlow, EventLoop};
use winit::keyboard::KeyCode;

use crate::draw::frame::FRAMES_IN_FLIGHT;
/// The largest window side X11 and Wayland accept.
const MAX_WINDOW_SIDE: u32 = 32767;

#[derive(Clone, Copy, Debug, PartialEq, Eq, ValueEnum)]
pub enum PresentMode {
    Fifo,
    Mailbox,
    Immediate,
}

#[derive(Args, Debug, Clone)]
pub struct ViewArgs {
    #[command(flatten)]
    pub common: CommonArgs,
    #[command(flatten)]
    pub textures: TextureArgs,
    #[command(flatten)]
    pub streamed: crate::app::cli::StreamedOptions,
    /// Exponential fog density per world unit (default: a haze at the terrain's scale).
    #[arg(long, value_name = "DENSITY", value_parser = crate::app::cli::non_negative, allow_negative_numbers = true)]
    pub fog: Option<f32>,
    #[arg(long, value_enum, default_value_t = PresentMode::Fifo)]
    pub present_mode: PresentMode,
    /// Exit after N frames.
    #[arg(long, value_name = "N", value_parser = crate::app::cli::at_least_one, allow_negative_numbers = true)]
    pub frames: Option<u64>,
    /// Fly north from the south edge, three quarters of the way across, over the run
    /// (with --frames) or every 60 seconds.
    #[arg(long)]
    pub flyover: bool,
    /// Write the last frame to this PNG before exiting.
    #[arg(long, value_name = "FILE.png")]
    pub screenshot: Option<PathBuf>,
    /// Record the flight: every frame's camera position and look-at point, written at
    /// exit in the pose format `bench --path FILE` replays.
    #[arg(long, value_name = "FILE")]
    pub record_path: Option<PathBuf>,
    /// Write a Chrome trace of both threads (Perfetto: the draw thread's phases, error
    /// requests, submissions, generations signalled and observed), as `bench` does; over
    /// an archive drawn streamed, the draw, IO and atlas threads' work.
    #[arg(long, value_name = "FILE.json")]
    pub trace: Option<PathBuf>,
    /// Start over this latitude and longitude (degrees, e.g. 46.85,-121.76 or
    /// "46.85 N 121.76 W"), as the panel's go-to does; georeferenced terrains only.
    #[arg(long, value_name = "LAT,LON", value_parser = crate::app::geo::parse_lat_lon, allow_hyphen_values = true)]
    pub go_to: Option<[f64; 2]>,
    /// Vertical exaggeration: heights drawn this many times their scale (the panel's
    /// slider changes it live).
    #[arg(long, value_name = "X", default_value = "1", value_parser = crate::app::cli::positive, allow_negative_numbers = true)]
    pub exaggeration: f32,
    /// Start in walk mode (follow the ground).
    #[arg(long)]
    pub walk: bool,
    /// Start with the on-screen panel hidden (H shows it).
    #[arg(long)]
    pub no_hud: bool,
    /// Resize the window at a frame, e.g. 20:800x600 (repeatable; for tests).
    #[arg(long, value_name = "FRAME:WxH", allow_hyphen_values = true)]
    pub resize_at: Vec<String>,
    /// After every frame, write the number of frames drawn so far to this file (replaced
    /// atomically): scripts that drive the viewer with synthetic input wait on it for
    /// their events to be seen, instead of sleeping.
    #[arg(long, value_name = "FILE")]
    pub frame_counter: Option<PathBuf>,
}

/// The viewer's start (and Home) view: over the south part of the terrain, above its
/// highest point, looking north over it.
fn start_view(hf: &Heightfield, mm: &MinMaxPyramid) -> (Vec3, Vec3) {
    let (wx, wz) = hf.world_extent();
    let [lo, hi] = mm.range().map(|r| r * hf.height_scale);
    let l = wx.max(wz);
    (Vec3::new(wx * 0.5, hi + 0.08 * l, wz * 0.92), Vec3::new(wx * 0.5, lo, wz * 0.35))
}

/// Everything that lives while the window is open, in drop order.
struct Gpu {
    hud: Hud,
    /// Per frame slot: the swapchain image's acquire semaphore. The slot's commands,
    /// fence and timestamps are the renderer's (`BlocksRenderer::submit_frame`).
    acquired: Vec<BinarySemaphore>,
    depth: Image,
    swapchain: Swapchain,
    renderer: BlocksRenderer,
    activity: Option<ErrorsActivity>,
    terrain: Arc<TerrainGpu>,
    surface: Surface,
    device: Arc<Device>,
}

impl Drop for Gpu {
    fn drop(&mut self) {
        // Nothing may be destroyed while the GPU still uses it; then stop the errors thread.
        let _ = self.device.wait_idle();
        if let Some(a) = self.activity.take() {
            let _ = a.stop();
        }
    }
}

struct App {
    args: ViewArgs,
    hf: Arc<Heightfield>,
    mm: MinMaxPyramid,
    layout: BlockLayout,
    base: Option<Texture>,
    detail: Option<Texture>,
    /// The window, what the event loop keeps of it, and the scripted run's options.
    win: WindowState,
    gpu: Option<Gpu>,
    ctl: Controller,
    /// Where Home puts the camera: position, yaw, pitch.
    home: (Vec3, f32, f32),
    /// The terrain's map frame (georeferenced inputs).
    geo: Option<crate::app::geo::Geo>,
    /// Vertical exaggeration (the panel's slider, `--exaggeration`) over the file's own
    /// height scale.
    exaggeration: f32,
    true_height_scale: f32,
    /// Horizontal speed over the last frame (world units per second), for the title.
    ground_speed: f32,
    shading: Shading,
    delta: f32,
    mode: ErrorMode,
    /// The sun asked for (the panel); the lighting map follows when no slider is held.
    sun: Option<Sun>,
    frozen: Option<Vec<DrawBlock>>,
    /// The draw thread's state: its error feed, caches and last selection.
    draw: DrawThread,
    frame: u64,
    slot: usize,
    /// Poses of the frames drawn, for --record-path.
    flight: Vec<(Vec3, Vec3)>,
    trace: Trace,
    last_frame: Instant,
    started: Instant,
    title_at: Instant,
    fps_frames: u64,
    last_stats: DrawStats,
    /// GPU time of the last finished frame (timestamps), when the device has them.
    last_gpu_ms: Option<f64>,
    /// How long the draw thread was blocked by the last finished frame: waiting for its
    /// slot (the frame two back) and for the queue's lock (ms).
    last_waits: (f64, f64),
    /// The frame submitted from each slot and not yet traced.
    slot_frames: [Option<u64>; FRAMES_IN_FLIGHT],
    last_blocks: usize,
    /// What occlusion culling did in the last traversed frame.
    last_occlusion: Option<crate::lod::occlusion::OcclusionReport>,
    /// The last frame's whole selection, nothing culled (frozen with Space).
    blocks: Vec<DrawBlock>,
    /// P presses not yet served.
    screenshots_asked: u64,
    stats: crate::app::outputs::ViewerReport,
}

impl PresentMode {
    pub fn vk(self) -> vk::PresentModeKHR {
        match self {
            PresentMode::Fifo => vk::PresentModeKHR::FIFO,
            PresentMode::Mailbox => vk::PresentModeKHR::MAILBOX,
            PresentMode::Immediate => vk::PresentModeKHR::IMMEDIATE,
        }
    }
}

impl ViewArgs {
    /// `--resize-at`'s resizes (frame, width, height), once `--size` and each of them is
    /// checked against what a window can be: refused before anything is loaded.
    fn window_resizes(&self) -> Result<Vec<(u64, u32, u32)>, InputError> {
        let mut resizes = Vec::new();
        for r in &self.resize_at {
            let parsed = r.split_once(':').and_then(|(f, s)| {
                let (w, h) = s.split_once('x')?;
                Some((f.parse().ok()?, w.parse().ok()?, h.parse().ok()?))
            });
            match parsed {
                Some((f, w, h)) if w > 0 && h > 0 => resizes.push((f, w, h)),
                Some(_) => return Err(InputError(format!("--resize-at {r}: the size must be at least 1x1"))),
                _ => return Err(InputError(format!("--resize-at {r}: expected FRAME:WxH"))),
            }
        }
        // Window systems take 16-bit signed sizes (winit panics beyond); the device's
        // image limit is checked once it exists.
        let sizes = self.common.view.frustum.size.iter().map(|&(w, h)| ("--size".to_string(), w, h));
        for (opt, w, h) in sizes.chain(resizes.iter().map(|&(f, w, h)| (format!("--resize-at {f}"), w, h))) {
            if w > MAX_WINDOW_SIDE || h > MAX_WINDOW_SIDE {
                return Err(InputError(format!(
                    "{opt} {w}x{h}: larger than a window can be ({MAX_WINDOW_SIDE} pixels a side)"
                )));
            }
        }
        Ok(resizes)
    }
}

/// The viewer over an archive drawn streamed ([`crate::app::stream_view`]), when it is
/// one: `--stream`, or larger than one image on the device.
fn view_archive(args: &ViewArgs, resizes: &[(u64, u32, u32)]) -> anyhow::Result<bool> {
    let max_side = || {
        let instance = Instance::new(&InstanceOptions { validation: false, extensions: Vec::new() }).ok()?;
        let options =
            DeviceOptions { gpu: args.common.device.gpu.clone(), queues: args.common.device.queues, swapchain: false };
        Device::new(instance, &options).ok().map(|d| d.max_image_dimension_2d() as usize)
    };
    // Without a device the in-memory path says why, as before. The viewer installs its
    // own stop handlers (a preparation's are not needed).
    let Some((archive, _)) =
        crate::app::stream::streamed_archive(&args.common.terrain, args.streamed.from_tiles(), || {
            max_side().unwrap_or(usize::MAX)
        })?
    else {
        return Ok(false);
    };
    let options = crate::app::stream_view::StreamViewOptions {
        common: args.common.clone(),
        textures: args.textures.clone(),
        fog: args.fog,
        present: args.present_mode.vk(),
        frames: args.frames,
        screenshot: args.screenshot.clone(),
        frame_counter: args.frame_counter.clone(),
        walk: args.walk,
        cache_mb: args.streamed.cache_mb(&archive.meta),
        gpu_mb: args.streamed.gpu_mb(&archive.meta),
        no_hud: args.no_hud,
        flyover: args.flyover,
        go_to: args.go_to,
        record_path: args.record_path.clone(),
        exaggeration: args.exaggeration,
        resizes: resizes.to_vec(),
        trace: args.trace.clone(),
    };
    crate::app::stream_view::view_streamed(&options, archive)?;
    Ok(true)
}

pub fn view(args: &ViewArgs) -> anyhow::Result<()> {
    args.common.terrain.check_terrain()?;
    if let Some(p) = args.screenshot.as_ref().filter(|p| !crate::app::outputs::is_png(p)) {
        return Err(
            InputError(format!("--screenshot {}: the screenshot is written as a .png file", p.display())).into()
        );
    }
    // Output paths are checked before the run, not when it ends: distinct files that
    // are not inputs.
    crate::app::outputs::check_outputs(
        &[
            ("--record-path", args.record_path.as_deref()),
            ("--frame-counter", args.frame_counter.as_deref()),
            ("--screenshot", args.screenshot.as_deref()),
            ("--trace", args.trace.as_deref()),
        ],
        &[
            ("--heightmap", args.common.terrain.heightmap.as_deref()),
            args.textures.inputs()[0],
            args.textures.inputs()[1],
        ],
    )?;
    let resizes = args.window_resizes()?;
    if view_archive(args, &resizes)? {
        return Ok(());
    }
    let mut hf = args.common.terrain.load_heightfield(None)?;
    let true_height_scale = hf.height_scale;
    hf.height_scale *= args.exaggeration;
    let layout = BlockLayout::of(&hf, args.common.block.k).map_err(InputError)?;
    let trace = match &args.trace {
        Some(p) => Trace::to_file(p).map_err(|e| InputError(format!("--trace {}: {e}", p.display())))?,
        None => Trace::off(),
    };
    // Ctrl-C (or SIGTERM) ends the session cleanly: the trace stays valid JSON.
    let stop = super::signals::Stop::install();
    let interrupted = stop.flag().clone();
    let Textures { base, detail } = args.textures.load(&hf)?;
    let mm = MinMaxPyramid::build(&hf);
    let (w, h) = args.common.view.frustum.size.unwrap_or((1280, 720));
    let cam = if args.common.view.position.is_none() && args.common.view.look_at.is_none() {
        // Inside the terrain's extent, above its highest point, looking over it: walk
        // mode (G) lands on ground from here.
        let (position, target) = start_view(&hf, &mm);
        Camera::look_at(position, target, args.common.view.frustum.fovy, w, h, near_plane(&hf))
    } else {
        args.common.view.camera(&hf, (w, h))?
    };
    let f = cam.forward;
    let (wx, wz) = hf.world_extent();
    let l = wx.max(wz);
    let fog = args.fog.unwrap_or_else(|| default_fog(&hf));
    let event_loop = EventLoop::new().map_err(|e| {
        anyhow::anyhow!("cannot open a window ({e}); is DISPLAY set? Use `vkterrain render` for headless output")
    })?;
    event_loop.set_control_flow(ControlFlow::Poll);
    let now = Instant::now();
    let geo = crate::app::geo::Geo::new(&hf.georef, hf.spacing);
    let ctl = Controller::new(cam.position, f, l / 60.0, args.walk);
    let mut app = App {
        args: args.clone(),
        hf: Arc::new(hf),
        mm,
        layout,
        base,
        detail,
        win: WindowState::new(interrupted, args.frames, args.screenshot.clone(), resizes),
        gpu: None,
        home: (ctl.position, ctl.yaw, ctl.pitch),
        geo,
        exaggeration: args.exaggeration,
        true_height_scale,
        ground_speed: 0.0,
        ctl,
        shading: args.textures.shade(Shading { fog_density: fog, ..Shading::default() }),
        delta: args.common.lod.delta,
        mode: args.common.error_mode.mode,
        sun: args.common.sun.0,
        frozen: None,
        draw: crate::app::commands::draw_thread(&args.common, trace.clone(), None)?,
        trace: trace.clone(),
        frame: 0,
        slot: 0,
        flight: Vec::new(),
        last_frame: now,
        started: now,
        title_at: now,
        fps_frames: 0,
        last_stats: DrawStats::default(),
        last_gpu_ms: None,
        last_waits: (0.0, 0.0),
        slot_frames: [None; FRAMES_IN_FLIGHT],
        last_blocks: 0,
        last_occlusion: None,
        blocks: Vec::new(),
        screenshots_asked: 0,
        stats: crate::app::outputs::ViewerReport::default(),
    };
    app.stats.state.exaggeration = args.exaggeration;
    if let Some([lat, lon]) = args.go_to {
        if app.geo.is_none() {
            return Err(InputError(format!(
                "--go-to: {} says nothing about where it is (no CRS or geotransform)",
                app.hf.source
            ))
            .into());
        }
        app.go_to(lat, lon).map_err(|e| InputError(format!("--go-to {e}")))?;
    }
    // Once the options are accepted. The same table as the panel's key help (F1).
    eprintln!("keys:");
    for (k, what) in crate::app::hud::KEYS {
        eprintln!("  {k:<13} {what}");
    }
    let mut windowed = Windowed(app);
    event_loop.run_app(&mut windowed)?;
    let mut app = windowed.0;
    let counter = app.gpu.as_ref().map(|g| g.device.instance.messages.clone());
    // Waits for the GPU, joins the errors thread, destroys the device and instance, so
    // that the object tracker's leak reports are counted below.
    drop(app.gpu.take());
    if let Some(p) = &args.trace {
        app.trace.finish().map_err(|e| anyhow::anyhow!("{}: {e}", p.display()))?;
        eprintln!("vkterrain: trace {}", p.display());
    }
    let validation = counter.as_ref().map(|c| c.count());
    let first_message = counter.as_ref().and_then(|c| c.messages().first().cloned());
    if let Some(e) = app.win.error.take() {
        return Err(e);
    }
    if let Some(path) = &args.record_path {
        crate::app::bench::record_poses(path, &app.flight)?;
    }
    let secs = app.started.elapsed().as_secs_f64();
    app.stats.frames = app.frame;
    app.stats.seconds = secs;
    app.stats.avg_fps = app.frame as f64 / secs.max(1e-9);
    app.stats.validation_messages = Some(validation.unwrap_or(0));
    app.stats.camera.final_position = app.ctl.position.to_array();
    (app.stats.camera.final_yaw, app.stats.camera.final_pitch) = (app.ctl.yaw, app.ctl.pitch);
    app.stats.state.final_delta = app.delta;
    app.stats.state.final_morph = app.draw.morph;
    app.stats.state.final_error_mode = app.mode.as_str();
    app.stats.camera.start_position = app.home.0.to_array();
    app.stats.camera.orbiting = app.ctl.orbit.is_some();
    (app.stats.state.frozen, app.stats.state.wireframe) = (app.frozen.is_some(), app.shading.wireframe);
    // In memory every block is within the bound (no tile to wait for).
    app.stats.worst_factor = 1.0;
    app.stats.interrupted = stop.requested();
    crate::out!("{}", serde_json::to_string(&app.stats)?)?;
    if let Some(n) = validation.filter(|&n| n > 0) {
        anyhow::bail!("{n} validation message(s); first: {}", first_message.unwrap_or_default());
    }
    if stop.requested() {
        return Err(Interrupted::by(&stop, "the session's figures printed above").into());
    }
    Ok(())
}

impl App {
    fn open(&mut self, event_loop: &ActiveEventLoop) -> anyhow::Result<()> {
        let requested = self.args.common.view.frustum.size.iter().map(|&(w, h)| ("--size".to_string(), w, h));
        let resizes = self.win.resizes.iter().map(|&(f, w, h)| (format!("--resize-at {f}"), w, h));
        let sizes: Vec<(String, u32, u32)> = requested.chain(resizes).collect();
        let title = format!("vkterrain: {}", self.hf.source);
        let (window, surface, device) =
            crate::app::controls::open_window(event_loop, &self.args.common, title, &sizes)?;
        Session::check_size(&device, &self.hf)?;
        self.args.textures.check_fits(self.base.as_ref(), self.detail.as_ref(), &device)?;
        let terrain = Arc::new(TerrainGpu::new(&device, &self.hf, &self.mm, self.base.as_ref(), self.detail.as_ref())?);
        let size = window.inner_size();
        let present = self.args.present_mode.vk();
        let swapchain = Swapchain::new(&device, &surface, (size.width, size.height), present, None)?;
        let depth = depth_image(&device, swapchain.extent)?;
        let renderer = BlocksRenderer::new(
            &device,
            &self.hf,
            &terrain,
            self.layout,
            swapchain.format,
            FRAMES_IN_FLIGHT,
            self.args.common.sun.0,
        )?;
        if let Some(sun) = renderer.lighting().sun() {
            eprintln!(
                "vkterrain: sun at azimuth {}, elevation {}: shadow and occlusion map in {:.0} ms",
                sun.azimuth,
                sun.elevation,
                renderer.lighting().last_ms()
            );
        }
        let mut hud = Hud::new(&device, &window, swapchain.format, DEPTH_FORMAT, FRAMES_IN_FLIGHT)?;
        hud.visible = !self.args.no_hud;
        if self.trace.enabled() {
            match crate::vk::QueryPool::calibrate(&device)? {
                Some(clock) => self.trace.set_gpu_clock(clock, device.queue_mode == crate::vk::QueueMode::Shared),
                None => eprintln!("vkterrain: note: no timestamp queries: the trace has no GPU tracks"),
            }
        }
        let activity = ErrorsActivity::start_with(
            &device,
            terrain.clone(),
            self.hf.clone(),
            self.layout,
            self.trace.clone(),
            self.args.common.error_pacing,
        )?;
        let acquired = (0..FRAMES_IN_FLIGHT).map(|_| BinarySemaphore::new(&device)).collect::<Result<Vec<_>, _>>()?;
        self.stats.queue_mode = device.queue_mode.as_str().into();
        self.stats.geometry_bytes = crate::app::commands::renderer_geometry_bytes(self.layout.k());
        self.stats.terrain = crate::app::outputs::TerrainFacts::of(&self.hf);
        self.stats.device = device.name.clone();
        let threads = traversal_threads(self.args.common.lod.traversal_threads, device.properties.device_type);
        self.draw.set_threads(threads)?;
        self.gpu =
            Some(Gpu { hud, acquired, depth, swapchain, renderer, activity: Some(activity), terrain, surface, device });
        self.win.window = Some(window);
        Ok(())
    }

    fn recreate_swapchain(&mut self) -> anyhow::Result<()> {
        let (Some(gpu), Some(window)) = (self.gpu.as_mut(), self.win.window.as_ref()) else { return Ok(()) };
        let size = window.inner_size();
        if size.width == 0 || size.height == 0 {
            return Ok(());
        }
        gpu.device.wait_idle()?;
        let present = self.args.present_mode.vk();
        let new = Swapchain::new(&gpu.device, &gpu.surface, (size.width, size.height), present, Some(&gpu.swapchain))?;
        gpu.swapchain = new;
        gpu.depth = depth_image(&gpu.device, gpu.swapchain.extent)?;
        gpu.hud.set_format(gpu.swapchain.format, DEPTH_FORMAT)?;
        self.win.swapchain_dirty = false;
        self.stats.resizes += 1;
        Ok(())
    }

    /// The camera for this frame: the flyover path or the controller.
    fn camera(&mut self, dt: f32) -> Camera {
        let gpu = self.gpu.as_ref().unwrap();
        let extent = gpu.swapchain.extent;
        if self.args.flyover {
            let t = flyover_time(self.args.frames, self.frame, self.started);
            let top = self.mm.range()[1] * self.hf.height_scale;
            self.ctl.fly_over(&*self.hf, top, t);
        } else {
            let before = self.ctl.position;
            self.ctl.update(&*self.hf, dt);
            let moved = self.ctl.position - before;
            self.ground_speed = if dt > 0.0 { Vec3::new(moved.x, 0.0, moved.z).length() / dt } else { 0.0 };
            if let Some((pivot, radius)) = self.ctl.orbit {
                let drift = ((self.ctl.position - pivot).length() - radius).abs() / radius;
                self.stats.camera.orbit_drift = self.stats.camera.orbit_drift.max(drift);
            }
        }
        let target = self.ctl.position + self.ctl.forward();
        Camera::look_at(
            self.ctl.position,
            target,
            self.args.common.view.frustum.fovy,
            extent.width,
            extent.height,
            near_plane(&self.hf),
        )
    }

    /// One frame ([`WindowApp::draw`]: the window is open and shown).
    fn draw_frame(&mut self) -> anyhow::Result<()> {
        if self.win.swapchain_dirty {
            self.recreate_swapchain()?;
        }
        let now = Instant::now();
        let interval = (now - self.last_frame).as_secs_f32();
        let dt = interval.min(0.25);
        self.last_frame = now;
        self.panel(interval)?;
        let cam = self.camera(dt);
        if self.args.record_path.is_some() {
            self.flight.push((cam.position, cam.position + cam.forward));
        }
        let frame_start = Instant::now();
        let slot_index = self.slot;
        let gpu = self.gpu.as_mut().unwrap();
        // The slot's previous frame must be done before its acquire semaphore is reused.
        if let Some(done) = gpu.renderer.wait_frame(slot_index)? {
            self.trace_frame(slot_index, &done);
        }
        // The frame step: the newest finished error generation (never waiting on the errors
        // queue after the first frame, which waits for data at its camera so the bound
        // holds from the start), the blocks (or the frozen ones), the submission.
        let gpu = self.gpu.as_mut().unwrap();
        let activity = gpu.activity.as_ref().unwrap();
        self.draw.feed.set_mode(self.mode);
        let terrain = LodTerrain { hf: &self.hf, mm: &self.mm, layout: &self.layout };
        let request = FrameRequest {
            frame: self.frame,
            cam: &cam,
            lod: LodChoice::Error,
            delta: self.delta,
            blocks: self.frozen.as_deref(),
        };
        let (hf, shading) = (&self.hf, &self.shading);
        let (screenshot_next, screenshots_asked) = (&mut self.win.screenshot_next, &mut self.screenshots_asked);
        let frame = self.draw.step(Some(activity), terrain, request, |blocks| {
            let acquired = gpu.acquired[slot_index].handle;
            // SAFETY: the swapchain and semaphore are live; the acquire semaphore of this
            // slot is unsignalled (its previous frame completed: waited for above).
            let acquire = unsafe {
                gpu.swapchain.loader.acquire_next_image(gpu.swapchain.handle, u64::MAX, acquired, vk::Fence::null())
            };
            let (image_index, suboptimal) = match acquire {
                Ok(r) => r,
                Err(vk::Result::ERROR_OUT_OF_DATE_KHR) => return Ok(None),
                Err(e) => return Err(e).vk("vkAcquireNextImageKHR").map_err(Into::into),
            };
            let extent = gpu.swapchain.extent;
            let screenshot = screenshot_next.take().or_else(|| {
                (*screenshots_asked > 0).then(|| {
                    *screenshots_asked -= 1;
                    crate::app::outputs::next_free_screenshot()
                })
            });
            let readback = match (&screenshot, gpu.swapchain.can_copy) {
                (Some(_), true) => Some(Buffer::new(
                    &gpu.device,
                    "screenshot",
                    extent.width as u64 * extent.height as u64 * 4,
                    vk::BufferUsageFlags::TRANSFER_DST,
                    gpu_allocator::MemoryLocation::GpuToCpu,
                )?),
                (Some(p), false) => {
                    tracing::warn!("{}: this swapchain cannot be copied from; no screenshot", p.display());
                    None
                }
                _ => None,
            };
            let dest = FrameDest {
                image: gpu.swapchain.images[image_index as usize],
                view: gpu.swapchain.views[image_index as usize],
                extent,
                depth: &gpu.depth,
                // The acquire semaphore orders this after the presentation engine's read.
                last_use: (vk::PipelineStageFlags2::COLOR_ATTACHMENT_OUTPUT, vk::AccessFlags2::NONE),
                copy_to: readback.as_ref().map(|b| b.handle),
                present: true,
            };
            let render_done = gpu.swapchain.render_done[image_index as usize];
            let waits = [vk::SemaphoreSubmitInfo::default()
                .semaphore(acquired)
                .stage_mask(vk::PipelineStageFlags2::COLOR_ATTACHMENT_OUTPUT)];
            let signals = [vk::SemaphoreSubmitInfo::default()
                .semaphore(render_done)
                .stage_mask(vk::PipelineStageFlags2::COLOR_ATTACHMENT_OUTPUT | vk::PipelineStageFlags2::COPY)];
            let hud = &mut gpu.hud;
            let mut hud_error = None;
            let mut draw_hud = |cmd| {
                if let Err(e) = hud.record(cmd, extent) {
                    hud_error = Some(e);
                }
            };
            let recording = Instant::now();
            gpu.renderer.submit_frame(
                slot_index,
                hf,
                &gpu.terrain,
                &dest,
                &cam,
                blocks,
                shading,
                Some(&mut draw_hud),
                FrameSync { wait: &waits, signal: &signals },
            )?;
            if let Some(e) = hud_error {
                return Err(e);
            }
            Ok(Some(Submitted { image_index, suboptimal, extent, screenshot, readback, render_done, recording }))
        })?;
        if let Some(n) = frame.taken {
            self.stats.error_generations = n;
        }
        self.stats.most_generations_in_flight = activity.most_in_flight();
        self.last_occlusion = frame.traversal.as_ref().and_then(|t| t.occlusion);
        // What Space freezes: the whole selection with nothing culled, as the camera will
        // move away from where it was hidden.
        let whole: Option<Vec<DrawBlock>> =
            frame.traversal.as_ref().map(|t| t.selection().map(|b| DrawBlock { hidden_parts: 0, ..*b }).collect());
        let (blocks, submitted) = frame.into_parts();
        let Some(Submitted { image_index, suboptimal, extent, screenshot, readback, render_done, recording }) =
            submitted
        else {
            self.win.swapchain_dirty = true;
            return Ok(());
        };
        let gpu = self.gpu.as_mut().unwrap();
        self.trace.complete(DRAW_TID, "record and submit", recording, Instant::now(), json!({"blocks": blocks.len()}));
        self.trace.instant(DRAW_TID, "submit (draw queue)", json!({"frame": self.frame}));
        self.slot_frames[slot_index] = Some(self.frame);
        let stats = gpu.renderer.pending(slot_index).unwrap_or_default();
        self.stats.state.hud_visible = gpu.hud.visible;
        self.stats.state.final_sun = gpu.renderer.lighting().sun().map(|s| [s.azimuth, s.elevation]);
        if gpu.hud.visible {
            self.stats.hud_frames += 1;
        }
        let presenting = Instant::now();
        let swapchains = [gpu.swapchain.handle];
        let indices = [image_index];
        let wait_present = [render_done];
        let present = vk::PresentInfoKHR::default()
            .wait_semaphores(&wait_present)
            .swapchains(&swapchains)
            .image_indices(&indices);
        let presented = {
            let _q = gpu.device.draw_queue.lock();
            // SAFETY: the queue is locked (external synchronization); handles are live.
            unsafe { gpu.swapchain.loader.queue_present(gpu.device.draw_queue.handle, &present) }
        };
        self.trace.complete(DRAW_TID, "present", presenting, Instant::now(), json!({"frame": self.frame}));
        self.trace.complete(DRAW_TID, "frame", frame_start, Instant::now(), json!({"frame": self.frame}));
        match presented {
            Ok(sub) => self.win.swapchain_dirty |= sub || suboptimal,
            Err(vk::Result::ERROR_OUT_OF_DATE_KHR) => self.win.swapchain_dirty = true,
            Err(e) => return Err(e).vk("vkQueuePresentKHR").map_err(Into::into),
        }
        if let (Some(path), Some(buf)) = (screenshot, readback) {
            let gpu = self.gpu.as_mut().unwrap();
            if let Some(done) = gpu.renderer.wait_frame(slot_index)? {
                self.trace_frame(slot_index, &done);
            }
            let gpu = self.gpu.as_ref().unwrap();
            let mut px = buf.mapped()?[..(extent.width * extent.height * 4) as usize].to_vec();
            if gpu.swapchain.format == vk::Format::B8G8R8A8_SRGB || gpu.swapchain.format == vk::Format::B8G8R8A8_UNORM {
                px.chunks_mut(4).for_each(|p| p.swap(0, 2));
            }
            save_png(&path, extent.width, extent.height, &px)?;
            eprintln!("vkterrain: screenshot {}", path.display());
            self.stats.screenshot = Some(path.display().to_string());
        }
        self.last_stats = stats;
        self.last_blocks = blocks.len();
        self.blocks = whole.unwrap_or(blocks);
        self.slot = (self.slot + 1) % FRAMES_IN_FLIGHT;
        self.frame += 1;
        if let Some(path) = &self.args.frame_counter {
            let frames = self.frame.to_string();
            crate::app::outputs::write_atomic(path, |tmp| {
                std::fs::write(tmp, &frames).map_err(|e| anyhow::anyhow!("{}: {e}", path.display()))
            })?;
        }
        self.fps_frames += 1;
        self.stats.last_triangles = stats.triangles;
        self.stats.last_draw_calls = stats.draw_calls;
        self.stats.last_blocks = self.last_blocks;
        self.update_title(&cam);
        Ok(())
    }

    /// Trace spans of a finished frame: its GPU time, the waits for the queue and for it.
    fn trace_frame(&mut self, slot: usize, done: &DrawStats) {
        let Some(frame) = self.slot_frames[slot].take() else { return };
        if let Some(g) = &self.gpu {
            let shared = g.device.queue_mode == crate::vk::QueueMode::Shared;
            if let Some(t) = done.gpu_ticks {
                self.trace.gpu_span(self.trace.gpu_tid(false, shared), "frame", t, json!({"frame": frame}));
            }
        }
        if let Some((asked, got)) = done.queue_lock {
            self.trace.complete(DRAW_TID, "wait (queue lock)", asked, got, json!({"frame": frame}));
        }
        if let Some((from, to)) = done.waited {
            self.trace.complete(DRAW_TID, "wait (frame slot)", from, to, json!({"frame": frame}));
        }
        self.last_gpu_ms = done.gpu_ms;
        self.draw.observe(done);
        let lock = done.queue_lock.map_or(0.0, |(a, g)| (g - a).as_secs_f64() * 1e3);
        self.last_waits = (done.wait_ms, lock);
    }

    /// The direction through the cursor, or the view's centre when the cursor is not in
    /// the window.
    fn cursor_ray(&self) -> Vec3 {
        let size = self.win.window.as_ref().map_or((0, 0), |w| (w.inner_size().width, w.inner_size().height));
        self.ctl.cursor_ray(self.win.cursor, size, self.args.common.view.frustum.fovy)
    }

    fn go_home(&mut self) {
        (self.ctl.position, self.ctl.yaw, self.ctl.pitch) = self.home;
        self.ctl.walk = false;
        self.ctl.orbit = None;
    }

    /// The state the panel and the keys both change.
    fn controls(&self) -> Controls {
        Controls {
            delta: self.delta,
            mode: self.mode,
            morph: self.draw.morph,
            occlusion: self.draw.occlusion,
            frozen: self.frozen.is_some(),
            wireframe: self.shading.wireframe,
            colour_by_lod: self.shading.colour_by_lod,
            deferred: self.shading.pixels == PixelPass::Deferred,
            fog_density: self.shading.fog_density,
            speed: self.ctl.speed,
            go_home: false,
            sun: self.sun,
            go_to: None,
            exaggeration: self.exaggeration,
        }
    }

    fn apply(&mut self, c: Controls) {
        if c.frozen != self.frozen.is_some() {
            self.frozen = c.frozen.then(|| self.blocks.clone());
        }
        self.delta = c.delta;
        self.mode = c.mode;
        self.draw.morph = c.morph;
        self.draw.occlusion = c.occlusion;
        self.shading.wireframe = c.wireframe;
        self.shading.colour_by_lod = c.colour_by_lod;
        self.shading.pixels = if c.deferred { PixelPass::Deferred } else { PixelPass::Forward };
        self.shading.fog_density = c.fog_density;
        self.ctl.speed = c.speed;
        self.sun = c.sun;
        if c.go_home {
            self.go_home();
        }
        if let Some([lat, lon]) = c.go_to {
            // The camera stays where it is; the panel's box keeps what was typed.
            if let Err(e) = self.go_to(lat, lon) {
                eprintln!("vkterrain: note: go-to {e}");
            }
        }
        self.exaggeration = c.exaggeration;
    }

    /// Draws heights at `self.exaggeration` times the file's scale: a new heightfield
    /// (the same samples, a new height scale) for the traversal and the frames, the
    /// errors activity restarted on it and its old data dropped (it bounded the old
    /// surface), the lighting map redrawn. Called when the slider is let go.
    fn apply_exaggeration(&mut self) -> anyhow::Result<()> {
        let scale = self.true_height_scale * self.exaggeration;
        if scale == self.hf.height_scale {
            return Ok(());
        }
        let mut hf = (*self.hf).clone();
        hf.height_scale = scale;
        let hf = Arc::new(hf);
        let Some(gpu) = self.gpu.as_mut() else { return Ok(()) };
        if let Some(old) = gpu.activity.take() {
            old.stop()?;
        }
        gpu.activity = Some(ErrorsActivity::start_with(
            &gpu.device,
            gpu.terrain.clone(),
            hf.clone(),
            self.layout,
            self.trace.clone(),
            self.args.common.error_pacing,
        )?);
        gpu.renderer.redraw_lighting(&hf)?;
        self.draw.feed.reset();
        self.hf = hf;
        self.stats.terrain = crate::app::outputs::TerrainFacts::of(&self.hf);
        self.stats.state.exaggeration = self.exaggeration;
        Ok(())
    }

    /// Moves the camera over a latitude and longitude, as high above the ground there as
    /// it is above the ground here (at least a fiftieth of the terrain's size), heading
    /// and pitch kept.
    fn go_to(&mut self, lat: f64, lon: f64) -> Result<(), String> {
        let (wx, wz) = self.hf.world_extent();
        let Some(geo) = self.geo.as_ref() else { return Ok(()) };
        let (x, z) = geo.world_on_terrain(lat, lon, (wx, wz))?;
        let ground = |x: f32, z: f32| self.hf.surface_height(x.clamp(0.0, wx), z.clamp(0.0, wz));
        let p = self.ctl.position;
        let above = (p.y - ground(p.x, p.z)).max(0.02 * wx.max(wz));
        self.ctl.position = Vec3::new(x, ground(x, z) + above, z);
        self.ctl.orbit = None;
        Ok(())
    }

    /// The terrain point under the cursor, when the cursor is over the terrain.
    fn cursor_ground(&self) -> Option<Vec3> {
        let (wx, wz) = self.hf.world_extent();
        let inside = |q: &Vec3| (0.0..=wx).contains(&q.x) && (0.0..=wz).contains(&q.z);
        self.win.cursor.map(|_| ground_hit(&*self.hf, self.ctl.position, self.cursor_ray())).filter(inside)
    }

    /// The panel's map section ([`crate::app::hud::Place::of`]).
    fn place(&self, cursor: Option<Vec3>) -> Option<crate::app::hud::Place> {
        let height = self.win.window.as_ref().map_or(1, |w| w.inner_size().height);
        let view = (height, self.args.common.view.frustum.fovy);
        Some(crate::app::hud::Place::of(self.geo.as_ref()?, &self.ctl, &*self.hf, cursor, view, self.exaggeration))
    }

    /// This frame's panel: the last frame's figures shown, its controls applied.
    /// `interval` is the time since the last frame began (the plotted frame time).
    fn panel(&mut self, interval: f32) -> anyhow::Result<()> {
        let (wx, wz) = self.hf.world_extent();
        let p = self.ctl.position;
        let mut readout = Readout {
            triangles: self.last_stats.triangles,
            draw_calls: self.last_stats.draw_calls,
            blocks: self.last_blocks,
            occlusion: self.last_occlusion.filter(|_| self.draw.occlusion),
            error_age: self.draw.feed.age_frames(self.frame),
            update_ms: self.draw.feed.update_ms(),
            generations: self.stats.error_generations,
            in_flight: self
                .gpu
                .as_ref()
                .and_then(|g| g.activity.as_ref())
                .map_or((0, true), |a| (a.most_in_flight(), a.paced())),
            queue_mode: self.stats.queue_mode.clone(),
            device: self.stats.device.clone(),
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
            above_ground: p.y - self.hf.surface_height(p.x.clamp(0.0, wx), p.z.clamp(0.0, wz)),
            ground_speed: self.ground_speed,
            gpu_frame_ms: self.last_gpu_ms,
            waits_ms: self.last_waits,
            ..Readout::default()
        };
        // One march along the cursor's ray a frame, for the panel and the exit figures.
        let cursor = self.geo.as_ref().and(self.cursor_ground());
        readout.place = self.place(cursor);
        if let Some(geo) = &self.geo {
            self.stats.camera.camera_lat_lon = geo.lat_lon(p.x, p.z);
            self.stats.camera.cursor_place = cursor.and_then(|q| {
                let [lat, lon] = geo.lat_lon(q.x, q.z)?;
                let ground_m = q.y / self.exaggeration;
                Some(serde_json::json!({ "lat": lat, "lon": lon, "ground_m": ground_m, "world": [q.x, q.y, q.z] }))
            });
        }
        if self.base.is_none() {
            let [lo, hi] = self.mm.range().map(|r| r * self.hf.height_scale);
            readout.legend =
                Some(crate::app::hud::Legend { absolute: self.hf.georef.absolute_heights, range_m: [lo, hi] });
        }
        let l = wx.max(wz);
        readout.ranges = Ranges { fog_default: default_fog(&self.hf), speed: (l / 6000.0, l / 6.0) };
        let before = self.controls();
        let mut after = before;
        let (Some(gpu), Some(window)) = (self.gpu.as_mut(), self.win.window.as_ref()) else { return Ok(()) };
        readout.panel_ms = gpu.hud.last_ms;
        readout.wireframe_available = gpu.device.features.wireframe;
        readout.lighting_ms = gpu.renderer.lighting().last_ms();
        readout.lit_sun = gpu.renderer.lighting().sun();
        if self.frame > 0 {
            let t = gpu.hud.now();
            gpu.hud.history.push(t, interval * 1e3);
        }
        gpu.hud.prepare(window, &readout, &mut after)?;
        if after != before {
            self.apply(after);
        }
        let gpu = self.gpu.as_mut().unwrap();
        if gpu.renderer.lighting().sun() != self.sun && !gpu.hud.pointer_busy() {
            gpu.renderer.set_sun(&self.hf, self.sun)?;
        }
        if !gpu.hud.pointer_busy() {
            self.apply_exaggeration()?;
        }
        Ok(())
    }

    /// Live statistics in the title bar, a few times a second.
    fn update_title(&mut self, cam: &Camera) {
        let elapsed = self.title_at.elapsed();
        if elapsed < Duration::from_millis(250) {
            return;
        }
        let fps = self.fps_frames as f64 / elapsed.as_secs_f64();
        self.title_at = Instant::now();
        self.fps_frames = 0;
        let age = self.draw.feed.age_frames(self.frame).map_or("-".to_string(), |a| a.to_string());
        let queue = self.gpu.as_ref().map_or("", |g| g.device.queue_mode.as_str());
        let (wx, wz) = self.hf.world_extent();
        let title = format!(
            "vkterrain | {fps:.1} fps {:.1} ms | {} tris {} draws {} blocks | delta {} {} {} | errors age {age} frames | queue {queue}{}{} | {:.0} above ground, {:.0}/s | ({:.0}, {:.0}, {:.0})",
            1000.0 / fps.max(1e-6),
            self.last_stats.triangles,
            self.last_stats.draw_calls,
            self.last_blocks,
            self.delta,
            self.mode.as_str(),
            if self.draw.morph { "morph" } else { "no morph" },
            if self.frozen.is_some() { " | FROZEN" } else { "" },
            if self.ctl.walk { " | walk" } else if self.ctl.orbit.is_some() { " | orbit" } else { "" },
            cam.position.y - self.hf.surface_height(cam.position.x.clamp(0.0, wx), cam.position.z.clamp(0.0, wz)),
            self.ground_speed,
            cam.position.x,
            cam.position.y,
            cam.position.z,
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
            KeyCode::KeyM => {
                self.mode = if self.mode == ErrorMode::Strict { ErrorMode::Paper } else { ErrorMode::Strict }
            }
            KeyCode::KeyN => self.draw.morph = !self.draw.morph,
            KeyCode::KeyC => self.draw.occlusion = !self.draw.occlusion,
            KeyCode::KeyX | KeyCode::KeyZ => {
                self.exaggeration =
                    crate::app::hud::exaggeration_key(code, self.exaggeration).unwrap_or(self.exaggeration)
            }
            KeyCode::KeyF => {
                self.shading.wireframe = !self.shading.wireframe;
                if self.gpu.as_ref().is_some_and(|g| !g.device.features.wireframe) {
                    eprintln!("vkterrain: note: this device has no wireframe (fillModeNonSolid)");
                }
            }
            KeyCode::KeyL => self.shading.colour_by_lod = !self.shading.colour_by_lod,
            KeyCode::KeyH | KeyCode::F1 => {
                if let Some(g) = self.gpu.as_mut() {
                    g.hud.on_key(code);
                }
            }
            KeyCode::Space => self.frozen = if self.frozen.is_some() { None } else { Some(self.blocks.clone()) },
            KeyCode::KeyG => {
                self.ctl.walk = !self.ctl.walk;
                self.ctl.clamp_to_ground(&*self.hf);
            }
            KeyCode::Home => self.go_home(),
            KeyCode::KeyO => {
                // Around the terrain point under the cursor (ahead when the cursor is
                // outside the window), turning to face it.
                let ray = self.cursor_ray();
                let turned = self.ctl.toggle_orbit(&*self.hf, ray);
                if self.ctl.orbit.is_some() {
                    self.stats.camera.orbit_aim_turn = turned;
                }
            }
            // One screenshot per frame, however fast P is pressed.
            KeyCode::KeyP => self.screenshots_asked += 1,
            _ => {}
        }
    }
}

/// A frame handed to the swapchain's queue: what presenting and the screenshot need.
struct Submitted {
    image_index: u32,
    suboptimal: bool,
    extent: vk::Extent2D,
    screenshot: Option<PathBuf>,
    readback: Option<Buffer>,
    render_done: vk::Semaphore,
    recording: Instant,
}

/// A haze at the terrain's scale: 18% fog across its width.
fn default_fog(hf: &Heightfield) -> f32 {
    let (wx, wz) = hf.world_extent();
    crate::lod::view::default_fog(wx.max(wz))
}

fn depth_image(device: &Arc<Device>, extent: vk::Extent2D) -> anyhow::Result<Image> {
    Ok(crate::draw::blocks::depth_target(device, "depth", extent)?)
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
        self.stats.camera.mouse_turn += turned;
        if self.ctl.orbit.is_some() {
            self.stats.camera.orbit_turn += turned;
        }
    }

    fn frames_drawn(&self) -> u64 {
        self.frame
    }

    fn draw(&mut self) -> anyhow::Result<()> {
        self.draw_frame()
    }
}
