//! The viewer's on-screen panel (egui): live figures with frame-time and fps plots, the
//! controls the keys also reach, a legend for the LOD colours and a key-help overlay.
//! It is drawn inside the frame's own rendering, after the terrain and the sky, so its
//! cost is part of the frame time the panel shows.

use crate::draw::lighting::Sun;
use crate::gpu::layout::LOD_PALETTE;
use crate::lod::gie::ErrorMode;
use crate::vk::{vk, CommandPool, Device};
use egui::{Color32, Pos2, Sense, Shape, Stroke, Vec2};
use egui_ash_renderer::allocator::GpuAllocator;
use egui_ash_renderer::{DynamicRendering, Options, RenderMode, Renderer};
use glam::Vec3;
use std::collections::VecDeque;
use std::sync::Arc;
use std::time::Instant;
use winit::event::WindowEvent;
use winit::window::Window;

/// The fog slider's end, in multiples of the default density.
pub const FOG_MAX_HAZE: f32 = 5.0;

/// Seconds of history in the plots.
pub const PLOT_SECONDS: f64 = 5.0;

/// Frame times over the last [`PLOT_SECONDS`].
#[derive(Debug, Default)]
pub struct FrameHistory {
    /// (seconds since start, frame time in ms), oldest first.
    samples: VecDeque<(f64, f32)>,
}

impl FrameHistory {
    /// Adds a frame that ended at `t` seconds and took `ms`; forgets frames older than
    /// the plot's span.
    pub fn push(&mut self, t: f64, ms: f32) {
        self.samples.push_back((t, ms));
        while self.samples.front().is_some_and(|&(s, _)| s < t - PLOT_SECONDS) {
            self.samples.pop_front();
        }
    }

    pub fn samples(&self) -> impl Iterator<Item = (f64, f32)> + '_ {
        self.samples.iter().copied()
    }

    /// Median and largest frame time in the span.
    pub fn median_max(&self) -> Option<(f32, f32)> {
        let mut v: Vec<f32> = self.samples.iter().map(|s| s.1).collect();
        if v.is_empty() {
            return None;
        }
        v.sort_by(f32::total_cmp);
        Some((v[v.len() / 2], v[v.len() - 1]))
    }

    /// Frames per second over each of the span's whole seconds (newest last), counting
    /// the frames that ended in it.
    pub fn fps_per_second(&self, now: f64) -> Vec<(f64, f32)> {
        let mut out = Vec::new();
        let mut end = now;
        while end - 1.0 >= now - PLOT_SECONDS {
            let n = self.samples.iter().filter(|&&(t, _)| t > end - 1.0 && t <= end).count();
            out.push((end, n as f32));
            end -= 1.0;
        }
        out.reverse();
        out
    }
}

/// What the panel shows (read only).
#[derive(Debug, Default, Clone)]
pub struct Readout {
    pub triangles: u64,
    pub draw_calls: u64,
    pub blocks: usize,
    /// What occlusion culling did in the last frame (when on).
    pub occlusion: Option<crate::lod::occlusion::OcclusionReport>,
    /// Frames since the camera was where the error data in use was computed.
    pub error_age: Option<u64>,
    /// GPU time of the newest error update, when the device has timestamps.
    pub update_ms: Option<f64>,
    pub generations: u64,
    /// Most generations in flight at once so far, and whether submissions are paced.
    pub in_flight: (u64, bool),
    pub queue_mode: String,
    pub device: String,
    pub camera_mode: &'static str,
    pub position: Vec3,
    pub above_ground: f32,
    pub ground_speed: f32,
    /// GPU time of the last finished frame (timestamps), when the device has them.
    pub gpu_frame_ms: Option<f64>,
    /// How long the draw thread was blocked by the last finished frame: for its frame
    /// slot and for the queue's lock (which the errors activity holds on a shared queue).
    pub waits_ms: (f64, f64),
    /// CPU time the panel took last frame (building, tessellating, recording).
    pub panel_ms: f32,
    /// Time the last lighting map took (ms), and the sun it was made for.
    pub lighting_ms: f64,
    pub lit_sun: Option<Sun>,
    pub wireframe_available: bool,
    /// The fog and speed sliders' ranges.
    pub ranges: Ranges,
    /// Where the camera and the cursor are on the map (georeferenced terrains only).
    pub place: Option<Place>,
    /// The colour ramp's legend (no base texture).
    pub legend: Option<Legend>,
    /// A terrain drawn from tiles: what its cache, atlas and errors did.
    pub tiles: Option<TilesReadout>,
}

/// The figures of a terrain drawn from tiles through a bounded cache: whether frames met
/// the bound (a block that should split is drawn as it is while its finer tile is read),
/// and what the cache, the atlas and the errors activity over it did.
#[derive(Debug, Default, Clone)]
pub struct TilesReadout {
    /// Frames drawn (this one included), and those with a block over the bound.
    pub frames: u64,
    pub frames_over_bound: u64,
    /// The largest factor over delta of a block drawn over the bound so far.
    pub worst_factor: f32,
    /// Whether this frame is within the bound.
    pub within_bound: bool,
    /// Tiles held in the host cache, its MB and budget.
    pub held: usize,
    pub cache_mb: f64,
    pub cache_budget_mb: u32,
    pub loaded: u64,
    pub evicted: u64,
    pub failed: u64,
    pub read_mb: f64,
    pub atlas_layers: u32,
    pub uploaded: u64,
    /// The errors activity's last generation over the atlas, if any yet.
    pub errors: Option<crate::errors::atlas_passes::Shaded>,
    /// Blocks drawn whose bound came from the errors activity's generation.
    pub blocks_bounded_by_errors: usize,
}

/// The panel's map section.
#[derive(Debug, Clone, Default)]
pub struct Place {
    pub crs: String,
    /// The camera's map position and its height above sea level (m).
    pub camera: String,
    pub camera_elevation_m: f32,
    /// The terrain point under the cursor: map position and ground height (m).
    pub cursor: Option<(String, f32)>,
    /// Metres per window pixel at the ground in the view's centre (the scale bar).
    pub metres_per_pixel: f32,
    /// Screen angle of north, clockwise from up (radians).
    pub north: f32,
}

impl Place {
    /// The map section for a camera `ctl` over `ground` placed by `geo`: the camera and
    /// `cursor` (the ground point under the cursor) on the map, the scale at the view's
    /// centre for a window `height` pixels high and a field of view of `fovy_deg`, and
    /// where north is on screen; heights in metres (world heights are `exaggeration`
    /// times them).
    pub fn of(
        geo: &crate::app::geo::Geo,
        ctl: &crate::app::controls::Controller,
        ground: &dyn crate::app::controls::Ground,
        cursor: Option<glam::Vec3>,
        (height, fovy_deg): (u32, f32),
        exaggeration: f32,
    ) -> Place {
        let p = ctl.position;
        let centre = crate::app::controls::ground_hit(ground, p, ctl.forward());
        let metres_per_pixel = (centre - p).length() * 2.0 * (fovy_deg.to_radians() * 0.5).tan() / height.max(1) as f32;
        let f = ctl.forward();
        let (up, right) = (glam::Vec2::new(f.x, f.z), glam::Vec2::new(-f.z, f.x));
        let n = glam::Vec2::from(geo.north());
        Place {
            crs: geo.crs().to_string(),
            camera: geo.describe(p.x, p.z),
            camera_elevation_m: p.y / exaggeration,
            cursor: cursor.map(|q| (geo.describe(q.x, q.z), q.y / exaggeration)),
            metres_per_pixel,
            north: n.dot(right).atan2(n.dot(up)),
        }
    }
}

/// What the ground colours mean: absolute heights (metres above sea level, water at or
/// below 0 m) or the terrain's own range.
#[derive(Debug, Clone, Copy, Default)]
pub struct Legend {
    pub absolute: bool,
    /// The terrain's lowest and highest ground (m).
    pub range_m: [f32; 2],
}

/// What the panel (and the keys) change.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Controls {
    pub delta: f32,
    pub mode: ErrorMode,
    pub morph: bool,
    /// Occlusion culling.
    pub occlusion: bool,
    pub frozen: bool,
    pub wireframe: bool,
    pub colour_by_lod: bool,
    /// Deferred shading (else forward; the wireframe and LOD-colour views are forward).
    pub deferred: bool,
    pub fog_density: f32,
    pub speed: f32,
    /// Set for one frame by the "Home" button.
    pub go_home: bool,
    /// Sun of the shadows and occlusion (`None`: off).
    pub sun: Option<Sun>,
    /// Set for one frame by the map's "go": latitude and longitude (degrees).
    pub go_to: Option<[f64; 2]>,
    /// Vertical exaggeration: heights drawn this many times their true scale.
    pub exaggeration: f32,
}

/// Ranges of the sliders that have no natural one.
#[derive(Debug, Default, Clone, Copy)]
pub struct Ranges {
    /// The default fog density (the slider is in multiples of it).
    pub fog_default: f32,
    pub speed: (f32, f32),
}

pub const KEYS: &[(&str, &str)] = &[
    ("W / S", "forward / back (orbit: in / out)"),
    ("A / D", "left / right"),
    ("Q / E", "down / up"),
    ("drag", "look around (orbit: turn around the centre)"),
    ("Shift, wheel", "faster; change the speed"),
    ("G", "walk on the ground / fly"),
    ("O", "orbit the terrain point under the cursor"),
    ("Home", "back to the start view"),
    ("[ and ]", "halve / double delta"),
    ("M", "strict / paper error mode"),
    ("Z / X", "less / more vertical exaggeration"),
    ("N", "geomorphing on / off"),
    ("C", "occlusion culling on / off"),
    ("F", "wireframe"),
    ("L", "colour blocks by LOD"),
    ("Space", "freeze the block list"),
    ("P", "screenshot (next free vkterrain-N.png)"),
    ("H", "hide / show this panel"),
    ("F1", "this help"),
    ("Esc", "quit"),
];

/// Builds the panel and the help overlay into `ctx`'s current pass.
pub fn build_ui(
    ctx: &egui::Context,
    show_panel: bool,
    show_help: &mut bool,
    readout: &Readout,
    history: &FrameHistory,
    now: f64,
    controls: &mut Controls,
) {
    if show_panel {
        panel_window(ctx, "vkterrain", |ui| panel(ui, readout, history, now, controls));
    }
    keys_window(ctx, show_help, KEYS);
}

/// The panel's window, top left, `body` in a scroll area that fits the window.
fn panel_window(ctx: &egui::Context, title: &str, body: impl FnOnce(&mut egui::Ui)) {
    egui::Window::new(title).default_pos([8.0, 8.0]).default_width(270.0).auto_sized().show(ctx, |ui| {
        ui.set_max_width(270.0);
        // Scrolls when the window is too small to show it whole (title bar and margins
        // take about 70 points).
        let room = (ctx.content_rect().height() - 80.0).max(40.0);
        // The minimum too: a window made small and then large again grows back.
        egui::ScrollArea::vertical().max_height(room).min_scrolled_height(room).show(ui, body);
    });
}

/// The key-help overlay (F1) listing `keys`, while `show_help`.
fn keys_window(ctx: &egui::Context, show_help: &mut bool, keys: &[(&str, &str)]) {
    if *show_help {
        egui::Window::new("Keys")
            .anchor(egui::Align2::CENTER_CENTER, [0.0, 0.0])
            .collapsible(false)
            .resizable(false)
            .open(show_help)
            .show(ctx, |ui| {
                egui::Grid::new("keys").num_columns(2).striped(true).show(ui, |ui| {
                    for (k, what) in keys {
                        ui.monospace(*k);
                        ui.label(*what);
                        ui.end_row();
                    }
                });
            });
    }
}

fn panel(ui: &mut egui::Ui, r: &Readout, history: &FrameHistory, now: f64, c: &mut Controls) {
    let ranges = r.ranges;
    let (median, max) = history.median_max().unwrap_or((0.0, 0.0));
    ui.label(format!("{:.1} fps, frame {median:.1} ms, max {max:.1} ms", 1000.0 / median.max(1e-3)));
    ui.label(format!("this panel: {:.2} ms CPU per frame", r.panel_ms));
    plot(ui, "frame ms", history.samples().collect(), now, Color32::LIGHT_GREEN);
    plot(ui, "fps", history.fps_per_second(now), now, Color32::LIGHT_BLUE);
    egui::Grid::new("figures").num_columns(2).show(ui, |ui| {
        let mut row = |k: &str, v: String| {
            ui.label(k);
            ui.monospace(v);
            ui.end_row();
        };
        row("GPU frame", r.gpu_frame_ms.map_or("- (no timestamps)".into(), |m| format!("{m:.1} ms")));
        // Frames from tiles are waited for one by one: no slot to wait for.
        if r.tiles.is_none() {
            row("draw waits", format!("{:.1} slot, {:.1} queue ms", r.waits_ms.0, r.waits_ms.1));
        }
        row("triangles", r.triangles.to_string());
        row("draw calls", format!("{} ({} blocks)", r.draw_calls, r.blocks));
        row(
            "occluded",
            match r.occlusion {
                None => "- (off)".into(),
                Some(o) => match o.skipped {
                    Some(why) => format!("- ({})", why.as_str()),
                    // Parts, those of blocks hidden whole included (`--block 3`: blocks).
                    None => format!("{} of {} parts", o.hidden_parts, o.tested_parts),
                },
            },
        );
        row("error age", r.error_age.map_or("-".into(), |a| format!("{a} frames")));
        row("error update", r.update_ms.map_or("- (no timestamps)".into(), |m| format!("{m:.1} ms GPU")));
        row("generations", r.generations.to_string());
        let (most, paced) = r.in_flight;
        row("in flight", format!("{most} at most, {}", if paced { "paced" } else { "free" }));
        // The name without the driver's details in brackets (it fits the panel).
        row("device", r.device.split(" (").next().unwrap_or_default().chars().take(24).collect());
        row("queues", r.queue_mode.clone());
        row("camera", r.camera_mode.to_string());
        row("position", format!("{:.0}, {:.0}, {:.0}", r.position.x, r.position.y, r.position.z));
        row("above ground", format!("{:.0}", r.above_ground));
        row("ground speed", format!("{:.0}/s", r.ground_speed));
    });
    if let Some(t) = &r.tiles {
        tiles_section(ui, t);
    }
    if let Some(p) = &r.place {
        map_section(ui, p, &mut c.go_to);
    }
    if let Some(l) = &r.legend {
        legend(ui, l);
    }
    ui.separator();
    delta_slider(ui, &mut c.delta);
    let memory = r.tiles.is_none();
    ui.horizontal(|ui| {
        ui.label("errors");
        ui.radio_value(&mut c.mode, ErrorMode::Strict, "strict");
        ui.radio_value(&mut c.mode, ErrorMode::Paper, "paper");
    });
    ui.horizontal(|ui| {
        ui.checkbox(&mut c.morph, "morph");
        ui.checkbox(&mut c.occlusion, "occlusion culling");
        ui.checkbox(&mut c.frozen, "freeze blocks");
    });
    ui.horizontal(|ui| {
        ui.add_enabled(r.wireframe_available, egui::Checkbox::new(&mut c.wireframe, "wireframe"))
            .on_disabled_hover_text("this device has no fillModeNonSolid");
        ui.checkbox(&mut c.colour_by_lod, "LOD colours");
    });
    let forward_only = c.wireframe || c.colour_by_lod;
    ui.add_enabled(!forward_only, egui::Checkbox::new(&mut c.deferred, "deferred shading"))
        .on_hover_text("shade each visible pixel once, after a depth-only pass over the blocks")
        .on_disabled_hover_text("wireframe and LOD colours are shaded forward");
    if c.colour_by_lod {
        lod_legend(ui);
    }
    let when = if memory { "errors recomputed on release" } else { "at once" };
    exaggeration_slider(ui, &mut c.exaggeration, when);
    fog_slider(ui, &mut c.fog_density, ranges.fog_default);
    let mut shadows = c.sun.is_some();
    ui.horizontal(|ui| {
        ui.checkbox(&mut shadows, "sun shadows and occlusion");
    });
    if shadows != c.sun.is_some() {
        c.sun = if shadows { Some(r.lit_sun.unwrap_or(Sun::DEFAULT)) } else { None };
    }
    if let Some(sun) = c.sun.as_mut() {
        ui.horizontal(|ui| {
            ui.label("sun az");
            ui.add(egui::Slider::new(&mut sun.azimuth, 0.0..=360.0).suffix("°").fixed_decimals(0));
        });
        ui.horizontal(|ui| {
            ui.label("sun el");
            ui.add(egui::Slider::new(&mut sun.elevation, 1.0..=89.0).suffix("°").fixed_decimals(0));
        });
        ui.small(format!("shadows are redrawn on release ({:.0} ms last time)", r.lighting_ms));
    }
    speed_slider(ui, &mut c.speed, ranges.speed);
    ui.horizontal(|ui| {
        if ui.button("Home").clicked() {
            c.go_home = true;
        }
        ui.small("F1 keys, H hides this panel");
    });
}

/// The panel's rows for a terrain drawn from tiles.
fn tiles_section(ui: &mut egui::Ui, t: &TilesReadout) {
    ui.separator();
    let bound = if t.within_bound { "within" } else { "OVER" };
    ui.colored_label(
        if t.within_bound { Color32::LIGHT_GREEN } else { Color32::from_rgb(255, 170, 60) },
        format!("this frame: {bound} the bound"),
    )
    .on_hover_text("over: a block that should split was drawn as it is, its finer tile not read yet");
    egui::Grid::new("tiles").num_columns(2).show(ui, |ui| {
        let mut row = |k: &str, v: String| {
            ui.label(k);
            ui.monospace(v);
            ui.end_row();
        };
        row("over the bound", format!("{} of {} frames", t.frames_over_bound, t.frames));
        // A block far over the bound next to the camera reaches huge factors.
        let worst =
            if t.worst_factor < 1e4 { format!("{:.2}", t.worst_factor) } else { format!("{:.2e}", t.worst_factor) };
        row("worst", format!("{worst} x delta"));
        row("tiles held", format!("{} ({:.0} of {} MB)", t.held, t.cache_mb, t.cache_budget_mb));
        row("tiles read", format!("{} ({:.0} MB)", t.loaded, t.read_mb));
        row("evicted", t.evicted.to_string());
        row("failed reads", t.failed.to_string());
        row("atlas", format!("{} layers, {} uploads", t.atlas_layers, t.uploaded));
        // Short rows: the panel's width is what a drag beside it must leave free.
        if let Some(e) = &t.errors {
            row("errors", format!("{} tiles, {:.2} M groups", e.tiles, e.groups as f64 / 1e6));
            let gpu = e.gpu_ms.map_or(String::new(), |ms| format!(", {ms:.1} ms"));
            row("read back", format!("{:.1} KB{gpu}", e.bytes_read_back as f64 / 1024.0));
            row("by errors", format!("{} blocks", t.blocks_bounded_by_errors));
        }
    });
}

/// The colour-by-LOD view's palette, level by level.
fn lod_legend(ui: &mut egui::Ui) {
    ui.horizontal_wrapped(|ui| {
        ui.label("LOD");
        for (i, col) in LOD_PALETTE.iter().enumerate() {
            let (rect, _) = ui.allocate_exact_size(Vec2::splat(12.0), Sense::hover());
            let rgb = |v: f32| (v * 255.0).round() as u8;
            ui.painter().rect_filled(rect, 2.0, Color32::from_rgb(rgb(col[0]), rgb(col[1]), rgb(col[2])));
            ui.label(if i + 1 == LOD_PALETTE.len() {
                format!("{i}, {}..", i + LOD_PALETTE.len())
            } else {
                i.to_string()
            });
        }
    });
    ui.small("0 is the finest level; colours repeat every 6 levels, mixed 60 % over the ground.");
}

/// The vertical exaggeration, over [`EXAGGERATION_RANGE`]; `when` says when a change
/// takes effect.
fn exaggeration_slider(ui: &mut egui::Ui, exaggeration: &mut f32, when: &str) {
    ui.horizontal(|ui| {
        ui.label("vertical x");
        let range = EXAGGERATION_RANGE[0]..=EXAGGERATION_RANGE[1];
        ui.add(egui::Slider::new(exaggeration, range).logarithmic(true).fixed_decimals(2))
            .on_hover_text(format!("vertical exaggeration: heights drawn this many times their scale ({when})"));
    });
}

/// The vertical exaggeration's range (the slider's, and Z / X's steps of 1.5 stop there).
pub(crate) const EXAGGERATION_RANGE: [f32; 2] = [0.25, 20.0];

/// The exaggeration after Z (less) or X (more), or None for another key.
pub(crate) fn exaggeration_key(code: winit::keyboard::KeyCode, exaggeration: f32) -> Option<f32> {
    match code {
        winit::keyboard::KeyCode::KeyX => Some((exaggeration * 1.5).min(EXAGGERATION_RANGE[1])),
        winit::keyboard::KeyCode::KeyZ => Some((exaggeration / 1.5).max(EXAGGERATION_RANGE[0])),
        _ => None,
    }
}

fn delta_slider(ui: &mut egui::Ui, delta: &mut f32) {
    ui.horizontal(|ui| {
        ui.label("delta (px)");
        ui.add(egui::Slider::new(delta, 0.0625..=64.0).logarithmic(true).clamping(egui::SliderClamping::Edits));
    });
}

/// The fog density, in multiples of the default haze `default` (a range that does not
/// follow the value).
fn fog_slider(ui: &mut egui::Ui, density: &mut f32, default: f32) {
    ui.horizontal(|ui| {
        ui.label("fog");
        let mut haze = *density / default.max(f32::MIN_POSITIVE);
        let changed = ui
            .add(
                egui::Slider::new(&mut haze, 0.0..=FOG_MAX_HAZE)
                    .suffix(" x default")
                    .fixed_decimals(2)
                    .clamping(egui::SliderClamping::Edits),
            )
            .changed();
        if changed {
            *density = haze * default;
        }
    });
}

fn speed_slider(ui: &mut egui::Ui, speed: &mut f32, (lo, hi): (f32, f32)) {
    ui.horizontal(|ui| {
        ui.label("speed");
        ui.add(
            egui::Slider::new(speed, lo..=hi)
                .logarithmic(true)
                .suffix("/s")
                .fixed_decimals(0)
                .clamping(egui::SliderClamping::Edits),
        );
    });
}

/// Keeps a mouse press and its release in different frames. At a few frames a second a
/// quick click arrives whole between two frames, and egui, seeing the button go down and
/// up in one frame, moves no slider; so a release that follows a press no frame has seen
/// yet is held back and given to the next frame.
#[derive(Debug)]
pub struct ClickSplitter<E> {
    press_unseen: bool,
    held: Option<E>,
    /// Whether the panel took the last press (the held release answers the same).
    pub pressed_on_panel: bool,
}

impl<E> Default for ClickSplitter<E> {
    fn default() -> Self {
        ClickSplitter { press_unseen: false, held: None, pressed_on_panel: false }
    }
}

impl<E: Clone> ClickSplitter<E> {
    /// A button event: what to do with it now.
    pub fn on_button(&mut self, pressed: bool, event: &E) -> Click<E> {
        if pressed {
            self.press_unseen = true;
            // A second click before any frame: the first one's release goes first.
            match self.held.take() {
                Some(release) => Click::PassAfter(release),
                None => Click::Pass,
            }
        } else if self.press_unseen && self.held.is_none() {
            self.held = Some(event.clone());
            Click::Hold { taken: self.pressed_on_panel }
        } else {
            Click::Pass
        }
    }

    /// A frame took its input: the press is seen; returns the release to give the next
    /// frame.
    pub fn frame_taken(&mut self) -> Option<E> {
        self.press_unseen = false;
        self.held.take()
    }
}

/// A texture update as a whole image. The renderer uploads a partial update after a
/// layout transition from UNDEFINED, which allows a GPU to discard the rest of the
/// texture (the font atlas's other glyphs); so `copies` keeps every texture, patches
/// are applied to the copy, and the whole copy is uploaded.
pub fn whole_image(
    copies: &mut std::collections::HashMap<egui::TextureId, egui::ColorImage>,
    id: egui::TextureId,
    delta: &egui::epaint::ImageDelta,
) -> egui::epaint::ImageDelta {
    let egui::ImageData::Color(patch) = &delta.image;
    match delta.pos {
        None => {
            copies.insert(id, (**patch).clone());
        }
        Some([x0, y0]) => {
            let [w, h] = patch.size;
            let whole =
                copies.entry(id).or_insert_with(|| egui::ColorImage::filled([x0 + w, y0 + h], Color32::TRANSPARENT));
            let ww = whole.size[0];
            for y in 0..h.min(whole.size[1].saturating_sub(y0)) {
                let n = w.min(ww.saturating_sub(x0));
                whole.pixels[(y0 + y) * ww + x0..][..n].copy_from_slice(&patch.pixels[y * w..][..n]);
            }
        }
    }
    egui::epaint::ImageDelta::full(copies[&id].clone(), delta.options)
}

/// What [`ClickSplitter::on_button`] decided.
#[derive(Debug, PartialEq)]
pub enum Click<E> {
    /// Pass the event on now.
    Pass,
    /// Pass this held release on first, then the event.
    PassAfter(E),
    /// Held back for the next frame; `taken`: the panel takes it (as it took the press).
    Hold { taken: bool },
}

/// Whether a window of the panel (the panel or the key help) was drawn at `pos` last frame.
pub fn panel_at(ctx: &egui::Context, pos: Pos2) -> bool {
    // The root of the frame is a background layer that covers everything.
    ctx.layer_id_at(pos).is_some_and(|l| l.order != egui::Order::Background)
}

/// A line plot of (time, value) over the last [`PLOT_SECONDS`], scaled to its largest value.
/// Map coordinates of the camera and the cursor, a scale bar, a north arrow and a go-to.
pub fn map_section(ui: &mut egui::Ui, p: &Place, go_to: &mut Option<[f64; 2]>) {
    ui.separator();
    egui::Grid::new("map").num_columns(2).show(ui, |ui| {
        let mut row = |k: &str, v: String| {
            ui.label(k);
            ui.monospace(v);
            ui.end_row();
        };
        row("CRS", p.crs.clone());
        row("camera", p.camera.clone());
        row("camera height", format!("{:.0} m above sea", p.camera_elevation_m));
        match &p.cursor {
            Some((at, h)) => {
                row("cursor", at.clone());
                row("ground there", format!("{h:.0} m"));
            }
            None => row("cursor", "- (not over the terrain)".into()),
        }
    });
    let ppp = ui.ctx().pixels_per_point();
    ui.horizontal(|ui| {
        // The bar in points: a window pixel is 1 / ppp points.
        if let Some((metres, pixels)) = crate::app::geo::scale_bar(p.metres_per_pixel, 120.0 * ppp) {
            let (rect, _) = ui.allocate_exact_size(Vec2::new(pixels / ppp, 10.0), Sense::hover());
            let stroke = egui::Stroke::new(2.0, Color32::WHITE);
            ui.painter().line_segment([rect.left_bottom(), rect.right_bottom()], stroke);
            ui.painter().line_segment([rect.left_top(), rect.left_bottom()], stroke);
            ui.painter().line_segment([rect.right_top(), rect.right_bottom()], stroke);
            ui.label(if metres >= 1000.0 { format!("{} km", metres / 1000.0) } else { format!("{metres} m") });
        }
        // North arrow, turned with the view.
        let (rect, _) = ui.allocate_exact_size(Vec2::splat(22.0), Sense::hover());
        let (s, cs) = p.north.sin_cos();
        let at = |along: f32, across: f32| {
            rect.center() + Vec2::new(along * s + across * cs, -along * cs + across * s) * 9.0
        };
        let painter = ui.painter();
        painter.add(egui::Shape::convex_polygon(
            vec![at(1.0, 0.0), at(-0.6, 0.5), at(-0.3, 0.0), at(-0.6, -0.5)],
            Color32::WHITE,
            egui::Stroke::NONE,
        ));
        painter.text(at(-1.2, 0.0), egui::Align2::CENTER_CENTER, "N", egui::FontId::proportional(9.0), Color32::WHITE);
    });
    let id = ui.id().with("go-to text");
    ui.horizontal(|ui| {
        ui.label("go to");
        let mut text = ui.data_mut(|d| d.get_temp::<String>(id)).unwrap_or_default();
        let edit = ui.add(egui::TextEdit::singleline(&mut text).desired_width(130.0).hint_text("lat, lon"));
        let go = ui.button("go").clicked() || (edit.lost_focus() && ui.input(|i| i.key_pressed(egui::Key::Enter)));
        if go {
            match crate::app::geo::parse_lat_lon(&text) {
                Ok(ll) => {
                    *go_to = Some(ll);
                    ui.data_mut(|d| d.remove::<String>(id.with("error")));
                }
                Err(e) => ui.data_mut(|d| {
                    d.insert_temp(id.with("error"), e);
                }),
            }
        }
        ui.data_mut(|d| d.insert_temp(id, text));
    });
    if let Some(e) = ui.data(|d| d.get_temp::<String>(id.with("error"))) {
        ui.small(e);
    }
}

/// Swatches of the colour ramp with the heights they stand for.
fn legend(ui: &mut egui::Ui, l: &Legend) {
    use crate::gpu::layout::{RAMP_COLOURS, RAMP_SNOW, RAMP_SNOW_FROM, RAMP_STOPS, RAMP_TOP_M, WATER_COLOUR};
    let metres = |u: f32| if l.absolute { u * RAMP_TOP_M } else { l.range_m[0] + u * (l.range_m[1] - l.range_m[0]) };
    let rgb = |c: [f32; 3]| {
        let v = |x: f32| (x * 255.0).round() as u8;
        Color32::from_rgb(v(c[0]), v(c[1]), v(c[2]))
    };
    ui.horizontal_wrapped(|ui| {
        let swatch = |ui: &mut egui::Ui, c: [f32; 3], text: String| {
            let (rect, _) = ui.allocate_exact_size(Vec2::splat(12.0), Sense::hover());
            ui.painter().rect_filled(rect, 2.0, rgb(c));
            ui.label(text);
        };
        swatch(ui, WATER_COLOUR, if l.absolute { "<= 0 m".into() } else { "lowest".into() });
        for (u, c) in RAMP_STOPS.iter().zip(RAMP_COLOURS) {
            swatch(ui, c, format!("{:.0} m", metres(*u)));
        }
        swatch(ui, RAMP_SNOW, format!(">= {:.0} m", metres(RAMP_SNOW_FROM[0])));
    });
    ui.small(if l.absolute {
        "ground colours by height above sea level; steep slopes are rock"
    } else {
        "ground colours span this terrain's heights (not known to be above sea level)"
    });
}

fn plot(ui: &mut egui::Ui, name: &str, points: Vec<(f64, f32)>, now: f64, colour: Color32) {
    let (rect, _) = ui.allocate_exact_size(Vec2::new(ui.available_width(), 44.0), Sense::hover());
    let painter = ui.painter_at(rect);
    painter.rect_filled(rect, 2.0, Color32::from_black_alpha(140));
    let top = points.iter().map(|p| p.1).fold(0.0f32, f32::max).max(1e-3) * 1.4;
    let at = |t: f64, v: f32| {
        let x = rect.left() + ((1.0 - (now - t) / PLOT_SECONDS) as f32).clamp(0.0, 1.0) * rect.width();
        Pos2::new(x, rect.bottom() - v / top * rect.height())
    };
    if points.len() > 1 {
        painter.add(Shape::line(points.iter().map(|&(t, v)| at(t, v)).collect(), Stroke::new(1.5, colour)));
    }
    let label = format!("{name}, last {PLOT_SECONDS:.0} s (top {top:.0})");
    painter.text(
        rect.left_top() + Vec2::new(3.0, 2.0),
        egui::Align2::LEFT_TOP,
        label,
        egui::FontId::proportional(10.0),
        Color32::GRAY,
    );
}

/// The panel's GPU side and input state. Fields drop in order: the renderer (which
/// holds a clone of the device's allocator) before the device.
pub struct Hud {
    renderer: Renderer<GpuAllocator>,
    uploads: CommandPool,
    state: egui_winit::State,
    ctx: egui::Context,
    primitives: Vec<egui::ClippedPrimitive>,
    pixels_per_point: f32,
    format: vk::Format,
    pub visible: bool,
    pub help: bool,
    pub history: FrameHistory,
    /// Where the cursor is in the window (egui points), from the latest event.
    cursor: Option<Pos2>,
    clicks: ClickSplitter<WindowEvent>,
    /// A copy of each texture, for uploading updates whole ([`whole_image`]).
    textures: std::collections::HashMap<egui::TextureId, egui::ColorImage>,
    started: Instant,
    /// CPU time of the last frame's panel work (ms).
    pub last_ms: f32,
    device: Arc<Device>,
}

impl Hud {
    /// `format` is the colour attachment's; `depth` the depth attachment's (the panel
    /// is drawn inside the terrain's rendering, which has one, without depth testing).
    pub fn new(
        device: &Arc<Device>,
        window: &Window,
        format: vk::Format,
        depth: vk::Format,
        frames_in_flight: usize,
    ) -> anyhow::Result<Self> {
        let renderer = Renderer::with_gpu_allocator(
            device.shared_allocator(),
            device.raw.clone(),
            Self::mode(format, depth),
            Options {
                // One vertex/index buffer per frame slot: a slot's buffers are rewritten
                // only after its fence (the frame two back) was waited for.
                in_flight_frames: frames_in_flight,
                enable_depth_test: false,
                enable_depth_write: false,
                srgb_framebuffer: is_srgb(format),
            },
        )
        .map_err(|e| anyhow::anyhow!("the on-screen panel's renderer: {e}"))?;
        let ctx = egui::Context::default();
        let max_side = device.max_image_dimension_2d() as usize;
        let state = egui_winit::State::new(
            ctx.clone(),
            egui::ViewportId::ROOT,
            window,
            Some(window.scale_factor() as f32),
            None,
            Some(max_side),
        );
        Ok(Hud {
            renderer,
            uploads: CommandPool::new(device, device.draw_queue.family)?,
            state,
            ctx,
            primitives: Vec::new(),
            pixels_per_point: 1.0,
            format,
            visible: true,
            help: false,
            cursor: None,
            clicks: ClickSplitter::default(),
            textures: Default::default(),
            history: FrameHistory::default(),
            started: Instant::now(),
            last_ms: 0.0,
            device: device.clone(),
        })
    }

    fn mode(format: vk::Format, depth: vk::Format) -> RenderMode {
        RenderMode::DynamicRendering(DynamicRendering {
            color_attachment_format: format,
            depth_attachment_format: Some(depth),
            stencil_attachment_format: None,
        })
    }

    /// After a swapchain change: rebuilds the pipeline if the colour format changed.
    pub fn set_format(&mut self, format: vk::Format, depth: vk::Format) -> anyhow::Result<()> {
        if format != self.format {
            self.renderer
                .set_render_mode(Self::mode(format, depth))
                .map_err(|e| anyhow::anyhow!("the on-screen panel's renderer: {e}"))?;
            self.format = format;
        }
        Ok(())
    }

    /// Passes a window event to the panel; true when the panel took it (a click or drag
    /// on it, typing into it), so the camera must not also act on it.
    pub fn on_event(&mut self, window: &Window, event: &WindowEvent) -> bool {
        if let WindowEvent::MouseInput { state, .. } = event {
            let pressed = *state == winit::event::ElementState::Pressed;
            match self.clicks.on_button(pressed, event) {
                Click::Hold { taken } => return taken,
                Click::PassAfter(release) => {
                    // Its answer was given when it was held.
                    let _ = self.state.on_window_event(window, &release);
                }
                Click::Pass => {}
            }
        }
        let consumed = self.state.on_window_event(window, event).consumed;
        let consumed = match event {
            WindowEvent::CursorMoved { position, .. } => {
                let ppp = window.scale_factor() as f32;
                self.cursor = Some(Pos2::new(position.x as f32 / ppp, position.y as f32 / ppp));
                consumed
            }
            WindowEvent::CursorLeft { .. } => {
                self.cursor = None;
                consumed
            }
            // egui decides from where the pointer was at its last frame; at a few frames
            // a second the cursor may have reached the panel since. Where it is now counts.
            WindowEvent::MouseInput { state: winit::event::ElementState::Pressed, .. }
            | WindowEvent::MouseWheel { .. } => consumed || self.cursor.is_some_and(|p| panel_at(&self.ctx, p)),
            _ => consumed,
        };
        if let WindowEvent::MouseInput { state: winit::event::ElementState::Pressed, .. } = event {
            self.clicks.pressed_on_panel = consumed;
        }
        consumed
    }

    /// Passes `event` to the panel ([`Hud::on_event`]); true when it took an input the
    /// camera must then not also act on (a key, a click, the wheel).
    pub fn takes_input(&mut self, window: &Window, event: &WindowEvent) -> bool {
        self.on_event(window, event)
            && matches!(
                event,
                WindowEvent::KeyboardInput { .. } | WindowEvent::MouseInput { .. } | WindowEvent::MouseWheel { .. }
            )
    }

    /// The panel's own keys: H hides or shows it, F1 the key help. True when `code` was
    /// one of them.
    pub fn on_key(&mut self, code: winit::keyboard::KeyCode) -> bool {
        match code {
            winit::keyboard::KeyCode::KeyH => self.visible = !self.visible,
            winit::keyboard::KeyCode::F1 => self.help = !self.help,
            _ => return false,
        }
        true
    }

    /// Whether a control of the panel is being dragged (the sun is redrawn on release).
    pub fn pointer_busy(&self) -> bool {
        self.ctx.egui_is_using_pointer()
    }

    /// Seconds since the panel was made (the plots' clock).
    pub fn now(&self) -> f64 {
        self.started.elapsed().as_secs_f64()
    }

    /// Builds this frame's panel (applying its controls to `controls`) and uploads any
    /// new font or image data. Call before recording the frame.
    pub fn prepare(&mut self, window: &Window, readout: &Readout, controls: &mut Controls) -> anyhow::Result<()> {
        self.prepare_with(window, |ctx, visible, help, history, now| {
            build_ui(ctx, visible, help, readout, history, now, controls)
        })
    }

    /// [`Hud::prepare`] with the panel built by `build(ctx, visible, help, history, now)`.
    fn prepare_with(
        &mut self,
        window: &Window,
        mut build: impl FnMut(&egui::Context, bool, &mut bool, &FrameHistory, f64),
    ) -> anyhow::Result<()> {
        let started = Instant::now();
        let input = self.state.take_egui_input(window);
        // A release held back from this frame's input goes into the next one.
        if let Some(release) = self.clicks.frame_taken() {
            let _ = self.state.on_window_event(window, &release);
        }
        let now = self.now();
        let (visible, mut help) = (self.visible, self.help);
        let history = &self.history;
        let output = self.ctx.run_ui(input, |ui| build(ui.ctx(), visible, &mut help, history, now));
        self.help = help;
        self.state.handle_platform_output(window, output.platform_output);
        let mut delta = output.textures_delta;
        if !delta.set.is_empty() || !delta.free.is_empty() {
            // Texture changes are rare (the font atlas at start, new glyphs): wait until
            // no frame uses the old data rather than keep it alive per frame.
            self.device.wait_idle()?;
            let _queue = self.device.draw_queue.lock();
            for (id, images) in &delta.set {
                let mut whole = None;
                for image in images {
                    whole = Some(whole_image(&mut self.textures, *id, image));
                }
                if let Some(image) = whole {
                    // The renderer submits on the draw queue (locked above) and waits for it.
                    self.renderer
                        .set_texture(self.device.draw_queue.handle, self.uploads.handle, *id, &image)
                        .map_err(|e| anyhow::anyhow!("the on-screen panel's textures: {e}"))?;
                }
            }
            for id in &delta.free {
                self.textures.remove(id);
                self.renderer.free_texture(*id).map_err(|e| anyhow::anyhow!("the on-screen panel's textures: {e}"))?;
            }
            delta.clear(); // applied
        }
        self.pixels_per_point = output.pixels_per_point;
        self.primitives = self.ctx.tessellate(output.shapes, output.pixels_per_point);
        self.last_ms = started.elapsed().as_secs_f32() * 1e3;
        Ok(())
    }

    /// Records the prepared panel into `cmd`, inside the frame's rendering.
    pub fn record(&mut self, cmd: vk::CommandBuffer, extent: vk::Extent2D) -> anyhow::Result<()> {
        let started = Instant::now();
        self.renderer
            .cmd_draw(cmd, extent, self.pixels_per_point, &self.primitives)
            .map_err(|e| anyhow::anyhow!("the on-screen panel: {e}"))?;
        self.last_ms += started.elapsed().as_secs_f32() * 1e3;
        Ok(())
    }
}

fn is_srgb(format: vk::Format) -> bool {
    matches!(format, vk::Format::B8G8R8A8_SRGB | vk::Format::R8G8B8A8_SRGB | vk::Format::A8B8G8R8_SRGB_PACK32)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn texture_patches_are_uploaded_whole() {
        use egui::epaint::ImageDelta;
        let mut copies = std::collections::HashMap::new();
        let id = egui::TextureId::Managed(0);
        let opts = egui::TextureOptions::default();
        let base = egui::ColorImage::filled([4, 3], Color32::RED);
        let d = whole_image(&mut copies, id, &ImageDelta::full(base, opts));
        assert_eq!(d.pos, None);
        let patch = egui::ColorImage::filled([2, 1], Color32::BLUE);
        let d = whole_image(&mut copies, id, &ImageDelta::partial([1, 2], patch, opts));
        assert_eq!(d.pos, None, "uploaded whole");
        let egui::ImageData::Color(img) = &d.image;
        assert_eq!(img.size, [4, 3]);
        let blue: Vec<usize> = (0..12).filter(|&i| img.pixels[i] == Color32::BLUE).collect();
        assert_eq!(blue, vec![9, 10], "the patch at (1, 2) and (2, 2), the rest kept");
        assert_eq!(img.pixels.iter().filter(|&&p| p == Color32::RED).count(), 10);
    }

    /// A press and release between two frames reach egui in two frames; a slow press
    /// (a frame between) and a double click before any frame keep their order.
    #[test]
    fn quick_clicks_are_split_across_frames() {
        let mut c = ClickSplitter::<&str>::default();
        assert_eq!(c.on_button(true, &"down"), Click::Pass);
        c.pressed_on_panel = true;
        assert_eq!(c.on_button(false, &"up"), Click::Hold { taken: true });
        assert_eq!(c.frame_taken(), Some("up"));
        assert_eq!(c.frame_taken(), None);
        // A frame between press and release: nothing held.
        assert_eq!(c.on_button(true, &"down"), Click::Pass);
        assert_eq!(c.frame_taken(), None);
        assert_eq!(c.on_button(false, &"up"), Click::Pass);
        // Two clicks before a frame: the first release goes before the second press.
        assert_eq!(c.on_button(true, &"down1"), Click::Pass);
        assert_eq!(c.on_button(false, &"up1"), Click::Hold { taken: true });
        assert_eq!(c.on_button(true, &"down2"), Click::PassAfter("up1"));
        assert_eq!(c.on_button(false, &"up2"), Click::Hold { taken: true });
        assert_eq!(c.frame_taken(), Some("up2"));
    }

    /// Why: egui moves a slider only when it sees the button down in a frame. A click on
    /// the delta slider's track, press and release in one pass, leaves delta alone; the
    /// same click split over two passes moves it.
    #[test]
    fn egui_needs_the_press_and_release_in_different_frames() {
        for split in [false, true] {
            let ctx = egui::Context::default();
            let mut c = controls();
            let readout = Readout { ranges: Ranges { fog_default: 0.1, speed: (1.0, 100.0) }, ..Readout::default() };
            let h = FrameHistory::default();
            let mut track = None;
            for pass in 0..5 {
                let mut events = Vec::new();
                if let Some(at) = track {
                    let button = |pressed| egui::Event::PointerButton {
                        pos: at,
                        button: egui::PointerButton::Primary,
                        pressed,
                        modifiers: Default::default(),
                    };
                    match (pass, split) {
                        (2, false) => events = vec![egui::Event::PointerMoved(at), button(true), button(false)],
                        (2, true) => events = vec![egui::Event::PointerMoved(at), button(true)],
                        (3, true) => events = vec![button(false)],
                        _ => {}
                    }
                }
                let input = egui::RawInput {
                    screen_rect: Some(egui::Rect::from_min_size(Pos2::ZERO, Vec2::new(1280.0, 1000.0))),
                    events,
                    ..Default::default()
                };
                let mut help = false;
                let mut out = ctx.run_ui(input, |ui| build_ui(ui.ctx(), true, &mut help, &readout, &h, 3.0, &mut c));
                out.textures_delta.clear();
                // Right of the "delta (px)" label, on the slider's track near its far end.
                for clipped in &out.shapes {
                    if let egui::epaint::Shape::Text(t) = &clipped.shape {
                        if t.galley.text() == "delta (px)" && track.is_none() {
                            let r = t.visual_bounding_rect();
                            track = Some(Pos2::new(r.right() + 90.0, r.center().y));
                        }
                    }
                }
            }
            assert_eq!(c.delta != 1.0, split, "split {split}: delta {}", c.delta);
        }
    }

    #[test]
    fn history_keeps_the_plot_span_and_reports_median_and_max() {
        let mut h = FrameHistory::default();
        for i in 0..100 {
            h.push(i as f64 * 0.1, if i == 95 { 50.0 } else { 10.0 + (i % 3) as f32 });
        }
        // 9.9 s now: frames from 4.9 s on remain (4.9, 5.0, ..., 9.9).
        assert_eq!(h.samples().count(), 51);
        assert!(h.samples().all(|(t, _)| t >= 9.9 - PLOT_SECONDS - 1e-9));
        assert_eq!(h.median_max(), Some((11.0, 50.0)));
        assert_eq!(FrameHistory::default().median_max(), None);
    }

    #[test]
    fn fps_counts_the_frames_of_each_second() {
        let mut h = FrameHistory::default();
        // 20 fps for the first 3 s, then 40 fps.
        let mut t = 0.0;
        while t < 3.0 {
            t += 0.05;
            h.push(t, 50.0);
        }
        while t < 6.0 {
            t += 0.025;
            h.push(t, 25.0);
        }
        let fps = h.fps_per_second(6.0);
        assert_eq!(fps.len(), PLOT_SECONDS as usize);
        let last = fps.last().unwrap().1;
        assert!((39.0..=41.0).contains(&last), "{fps:?}");
        let first = fps.first().unwrap().1; // 1..2 s
        assert!((19.0..=21.0).contains(&first), "{fps:?}");
    }

    fn controls() -> Controls {
        Controls {
            delta: 1.0,
            mode: ErrorMode::Strict,
            morph: true,
            occlusion: true,
            frozen: false,
            wireframe: false,
            colour_by_lod: false,
            deferred: true,
            fog_density: 0.1,
            speed: 10.0,
            go_home: false,
            sun: Some(Sun::DEFAULT),
            go_to: None,
            exaggeration: 1.0,
        }
    }

    /// Runs the panel headless for a few passes; in the last, clicks the centre of the
    /// text `click_on` as laid out in the pass before (or a point outside the panel).
    /// Returns the controls after and the number of shapes of the last pass.
    fn run(show: bool, click_on: Result<&str, Pos2>) -> (Controls, usize) {
        run_on(Vec2::new(1280.0, 1000.0), show, click_on, 0.0, false)
    }

    /// As [`run`] on a screen of `screen` points, with the mouse wheel turned by
    /// `scroll` points over the panel in the second pass; `shrunk`: the first passes on
    /// a 400 x 300 screen (a window made small, then large again).
    fn run_on(screen: Vec2, show: bool, click_on: Result<&str, Pos2>, scroll: f32, shrunk: bool) -> (Controls, usize) {
        let readout = Readout { ranges: Ranges { fog_default: 0.1, speed: (1.0, 100.0) }, ..Readout::default() };
        run_with(&readout, screen, show, click_on, scroll, shrunk)
    }

    /// As [`run_on`] with the panel showing `readout`.
    fn run_with(
        readout: &Readout,
        screen: Vec2,
        show: bool,
        click_on: Result<&str, Pos2>,
        scroll: f32,
        shrunk: bool,
    ) -> (Controls, usize) {
        // A second apart, so that smoothed scrolling has finished before the click.
        const PASSES: usize = 20;
        use egui::epaint::Shape as S;
        let ctx = egui::Context::default();
        let mut c = controls();
        let mut h = FrameHistory::default();
        for i in 0..30 {
            h.push(i as f64 * 0.1, 16.0);
        }
        let mut shapes = 0;
        let mut target = click_on.err();
        for pass in 0..PASSES {
            let mut events = match (pass, target) {
                (p, Some(at)) if p == PASSES - 1 => {
                    let click = |pressed| egui::Event::PointerButton {
                        pos: at,
                        button: egui::PointerButton::Primary,
                        pressed,
                        modifiers: Default::default(),
                    };
                    vec![egui::Event::PointerMoved(at), click(true), click(false)]
                }
                _ => Vec::new(),
            };
            if (1..PASSES / 2).contains(&pass) && scroll != 0.0 {
                events.push(egui::Event::PointerMoved(Pos2::new(100.0, 200.0)));
                events.push(egui::Event::MouseWheel {
                    unit: egui::MouseWheelUnit::Point,
                    delta: Vec2::new(0.0, -scroll),
                    modifiers: Default::default(),
                    phase: egui::TouchPhase::Move,
                });
            }
            let input = egui::RawInput {
                screen_rect: Some(egui::Rect::from_min_size(
                    Pos2::ZERO,
                    if shrunk && pass < 4 { Vec2::new(400.0, 300.0) } else { screen },
                )),
                time: Some(pass as f64),
                predicted_dt: 1.0,
                events,
                ..Default::default()
            };
            let mut help = false;
            let mut out = ctx.run_ui(input, |ui| build_ui(ui.ctx(), show, &mut help, readout, &h, 3.0, &mut c));
            out.textures_delta.clear(); // nothing to upload headless
            shapes = out.shapes.len();
            if let Ok(text) = click_on {
                for clipped in &out.shapes {
                    if let S::Text(t) = &clipped.shape {
                        if t.galley.text() == text {
                            target = Some(t.visual_bounding_rect().center());
                        }
                    }
                }
            }
        }
        if let Ok(text) = click_on {
            assert!(target.is_some(), "no text {text:?} in the panel on {screen:?}");
        }
        (c, shapes)
    }

    /// The map section's go-to, driven headless: click into the box, type, click "go":
    /// the controls carry the latitude and longitude typed; a bad entry shows why and
    /// goes nowhere.
    fn go_to_after_typing(typed: &str) -> (Controls, Vec<String>) {
        use egui::epaint::Shape as S;
        let ctx = egui::Context::default();
        let mut c = controls();
        let place = Place { crs: "EPSG:4326".into(), camera: "x".into(), metres_per_pixel: 10.0, ..Place::default() };
        let readout = Readout {
            ranges: Ranges { fog_default: 0.1, speed: (1.0, 100.0) },
            place: Some(place),
            legend: Some(Legend { absolute: true, range_m: [0.0, 4000.0] }),
            ..Readout::default()
        };
        let h = FrameHistory::default();
        let (mut field, mut button, mut texts) = (None, None, Vec::new());
        let click = |at: Pos2| {
            let b = |pressed| egui::Event::PointerButton {
                pos: at,
                button: egui::PointerButton::Primary,
                pressed,
                modifiers: Default::default(),
            };
            vec![egui::Event::PointerMoved(at), b(true), b(false)]
        };
        for pass in 0..12 {
            let events = match pass {
                4 => click(field.expect("the go-to box")),
                6 => vec![egui::Event::Text(typed.into())],
                8 => click(button.expect("the go button")),
                _ => Vec::new(),
            };
            let input = egui::RawInput {
                screen_rect: Some(egui::Rect::from_min_size(Pos2::ZERO, Vec2::new(1280.0, 1400.0))),
                time: Some(pass as f64),
                predicted_dt: 1.0,
                events,
                ..Default::default()
            };
            let mut help = false;
            if pass == 9 {
                // The go is for one frame: the viewer applies it and hands fresh controls.
                assert!(c.go_to.is_some() || !texts.is_empty());
            }
            let mut out = ctx.run_ui(input, |ui| build_ui(ui.ctx(), true, &mut help, &readout, &h, 3.0, &mut c));
            out.textures_delta.clear();
            texts.clear();
            for clipped in &out.shapes {
                if let S::Text(t) = &clipped.shape {
                    let r = t.visual_bounding_rect();
                    match t.galley.text() {
                        "lat, lon" => field = Some(r.center()),
                        "go" => button = Some(r.center()),
                        other => texts.push(other.to_string()),
                    }
                }
            }
        }
        (c, texts)
    }

    #[test]
    fn the_map_section_goes_to_what_is_typed() {
        let (c, texts) = go_to_after_typing("46.85 N, 121.76 W");
        assert_eq!(c.go_to, Some([46.85, -121.76]));
        assert!(texts.iter().any(|t| t == "EPSG:4326"), "{texts:?}");
        assert!(texts.iter().any(|t| t == "1 km"), "scale bar at 10 m a pixel: {texts:?}");
        assert!(texts.iter().any(|t| t == "<= 0 m") && texts.iter().any(|t| t == "1750 m"), "legend: {texts:?}");
        let (c, texts) = go_to_after_typing("somewhere");
        assert_eq!(c.go_to, None);
        assert!(texts.iter().any(|t| t.contains("expected latitude, longitude")), "{texts:?}");
    }

    #[test]
    fn the_panel_draws_when_shown_and_nothing_when_hidden() {
        let (c, shown) = run(true, Err(Pos2::new(1000.0, 600.0)));
        assert!(shown > 0);
        assert_eq!(c, controls(), "a click outside the panel changes nothing");
        let (_, hidden) = run(false, Err(Pos2::new(1000.0, 600.0)));
        assert_eq!(hidden, 0);
    }

    /// The press that starts a drag counts as the panel's when the cursor is over the
    /// panel as drawn last frame, wherever egui last saw the pointer.
    #[test]
    fn the_panel_is_found_where_it_was_drawn() {
        let ctx = egui::Context::default();
        let mut c = controls();
        let readout = Readout { ranges: Ranges { fog_default: 0.1, speed: (1.0, 100.0) }, ..Readout::default() };
        let h = FrameHistory::default();
        for show in [true, false] {
            for _ in 0..2 {
                let input = egui::RawInput {
                    screen_rect: Some(egui::Rect::from_min_size(Pos2::ZERO, Vec2::new(1280.0, 720.0))),
                    ..Default::default()
                };
                let mut help = false;
                let mut out = ctx.run_ui(input, |ui| build_ui(ui.ctx(), show, &mut help, &readout, &h, 3.0, &mut c));
                out.textures_delta.clear();
            }
            assert_eq!(panel_at(&ctx, Pos2::new(100.0, 20.0)), show, "the panel's title bar (shown: {show})");
            assert_eq!(panel_at(&ctx, Pos2::new(100.0, 300.0)), show, "the panel's middle (shown: {show})");
            assert!(
                !panel_at(&ctx, Pos2::new(900.0, 400.0)),
                "beside the panel: {:?}",
                ctx.layer_id_at(Pos2::new(900.0, 400.0))
            );
        }
    }

    #[test]
    fn the_panel_controls_change_the_state() {
        let (c, _) = run(true, Ok("morph"));
        assert_eq!(c, Controls { morph: false, ..controls() });
        let (c, _) = run(true, Ok("occlusion culling"));
        assert_eq!(c, Controls { occlusion: false, ..controls() });
        let (c, _) = run(true, Ok("LOD colours"));
        assert_eq!(c, Controls { colour_by_lod: true, ..controls() });
        let (c, _) = run(true, Ok("deferred shading"));
        assert_eq!(c, Controls { deferred: false, ..controls() });
        let (c, _) = run(true, Ok("paper"));
        assert_eq!(c, Controls { mode: ErrorMode::Paper, ..controls() });
        let (c, _) = run(true, Ok("Home"));
        assert_eq!(c, Controls { go_home: true, ..controls() });
        let (c, _) = run(true, Ok("sun shadows and occlusion"));
        assert_eq!(c, Controls { sun: None, ..controls() });
        // On a small screen the panel scrolls: the end of it is reached with the wheel.
        let small = Vec2::new(640.0, 480.0);
        let (c, _) = run_on(small, true, Ok("Home"), 2000.0, false);
        assert_eq!(c, Controls { go_home: true, ..controls() });
        // Made small and large again, the panel is whole again without scrolling.
        let (c, _) = run_on(Vec2::new(1280.0, 1000.0), true, Ok("Home"), 0.0, true);
        assert_eq!(c, Controls { go_home: true, ..controls() });
        // Wireframe is greyed out on a device without it (the readout's default).
        let (c, _) = run(true, Ok("wireframe"));
        assert_eq!(c, controls());
    }

    /// A terrain drawn from tiles: the same panel with the tiles' rows, and every control.
    #[test]
    fn the_panel_of_a_terrain_drawn_from_tiles_has_every_control() {
        let tiles = TilesReadout { frames: 7, frames_over_bound: 2, worst_factor: 1.5, ..TilesReadout::default() };
        let readout = Readout {
            ranges: Ranges { fog_default: 0.1, speed: (1.0, 100.0) },
            wireframe_available: true,
            tiles: Some(tiles),
            ..Readout::default()
        };
        let screen = Vec2::new(1280.0, 1400.0);
        let click = |text| run_with(&readout, screen, true, Ok(text), 0.0, false).0;
        assert_eq!(click("2 of 7 frames"), controls(), "the tiles' rows are shown");
        assert_eq!(click("paper"), Controls { mode: ErrorMode::Paper, ..controls() });
        assert_eq!(click("occlusion culling"), Controls { occlusion: false, ..controls() });
        assert_eq!(click("morph"), Controls { morph: false, ..controls() });
        assert_eq!(click("freeze blocks"), Controls { frozen: true, ..controls() });
        assert_eq!(click("wireframe"), Controls { wireframe: true, ..controls() });
        assert_eq!(click("deferred shading"), Controls { deferred: false, ..controls() });
        assert_eq!(click("sun shadows and occlusion"), Controls { sun: None, ..controls() });
        assert_eq!(click("Home"), Controls { go_home: true, ..controls() });
    }
}
