//! The streamed viewer's on-screen panel ([`crate::app::stream_view`]): the in-memory
//! viewer's panel ([`crate::app::hud`], the same egui renderer, plots and sliders) with
//! what streaming does instead of what the errors activity does: frames drawn over the
//! bound and the worst factor (SPEC 8: a block whose finer tile is not held yet), the
//! tiles held, read, evicted and uploaded, and the bytes read.

use crate::app::hud::{
    delta_slider, exaggeration_slider, fog_slider, keys_window, legend, lod_legend, map_section, panel_window, plot,
    speed_slider, FrameHistory, Legend, Place,
};
use egui::Color32;
use glam::Vec3;

/// What the panel shows (read only).
#[derive(Debug, Default, Clone)]
pub struct StreamReadout {
    pub blocks: usize,
    pub triangles: u64,
    pub frames: u64,
    /// Frames drawn with a block over the bound, and the largest error / delta of one.
    pub frames_over_bound: u64,
    pub worst_factor: f32,
    /// Whether the last frame was within the bound.
    pub within_bound: bool,
    pub tiles_held: usize,
    pub cache_mb: f64,
    pub cache_budget_mb: u32,
    pub tiles_loaded: u64,
    pub tiles_evicted: u64,
    pub tiles_failed: u64,
    pub read_mb: f64,
    pub atlas_layers: u32,
    pub uploaded_tiles: u64,
    /// The errors activity: its last generation over the atlas, and this frame's blocks
    /// whose error came from it.
    pub errors: Option<crate::errors::atlas_passes::Shaded>,
    pub blocks_bounded_by_errors: usize,
    pub device: String,
    pub queue_mode: String,
    /// "flyover", "walk" or "fly".
    pub camera: &'static str,
    pub position: Vec3,
    pub above_ground: f32,
    /// CPU time the panel took last frame.
    pub panel_ms: f32,
    pub legend: Option<Legend>,
    /// Where the camera and the cursor are on the map (georeferenced terrains only).
    pub place: Option<Place>,
    /// The fog slider's unit (the default density) and the speed slider's range.
    pub fog_default: f32,
    pub speed_range: (f32, f32),
}

/// What the panel (and the keys) change.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct StreamControls {
    pub delta: f32,
    pub fog_density: f32,
    pub speed: f32,
    /// Vertical exaggeration (applied at once: no errors to recompute).
    pub exaggeration: f32,
    /// Blocks tinted by their LOD.
    pub colour_by_lod: bool,
    /// Set for one frame by the "Home" button.
    pub go_home: bool,
    /// Set for one frame by the map section's go-to: a latitude and longitude.
    pub go_to: Option<[f64; 2]>,
}

pub const STREAM_KEYS: &[(&str, &str)] = &[
    ("W / S", "forward / back"),
    ("A / D", "left / right"),
    ("Q / E", "down / up"),
    ("drag", "look around"),
    ("Shift, wheel", "faster; change the speed"),
    ("G", "walk on the ground / fly"),
    ("Home", "back to the start view"),
    ("[ and ]", "halve / double delta"),
    ("Z / X", "less / more vertical exaggeration"),
    ("N", "geomorphing on / off"),
    ("O", "orbit the ground point under the cursor / fly"),
    ("Space", "freeze the drawn blocks / follow the camera"),
    ("F", "wireframe"),
    ("L", "colour blocks by LOD"),
    ("P", "screenshot (next free vkterrain-N.png)"),
    ("H", "hide / show this panel"),
    ("F1", "this help"),
    ("Esc", "quit"),
];

/// Builds the panel and the help overlay into `ctx`'s current pass.
pub fn build_stream_ui(
    ctx: &egui::Context,
    show_panel: bool,
    show_help: &mut bool,
    r: &StreamReadout,
    history: &FrameHistory,
    now: f64,
    c: &mut StreamControls,
) {
    if show_panel {
        panel_window(ctx, "vkterrain (streamed)", |ui| panel(ui, r, history, now, c));
    }
    keys_window(ctx, show_help, STREAM_KEYS);
}

fn panel(ui: &mut egui::Ui, r: &StreamReadout, history: &FrameHistory, now: f64, c: &mut StreamControls) {
    let (median, max) = history.median_max().unwrap_or((0.0, 0.0));
    ui.label(format!("{:.1} fps, frame {median:.1} ms, max {max:.1} ms", 1000.0 / median.max(1e-3)));
    ui.label(format!("this panel: {:.2} ms CPU per frame", r.panel_ms));
    plot(ui, "frame ms", history.samples().collect(), now, Color32::LIGHT_GREEN);
    plot(ui, "fps", history.fps_per_second(now), now, Color32::LIGHT_BLUE);
    let bound = if r.within_bound { "within" } else { "OVER" };
    ui.colored_label(
        if r.within_bound { Color32::LIGHT_GREEN } else { Color32::from_rgb(255, 170, 60) },
        format!("this frame: {bound} the bound"),
    )
    .on_hover_text("over: a block that should split was drawn as it is, its finer tile not read yet");
    egui::Grid::new("stream figures").num_columns(2).show(ui, |ui| {
        let mut row = |k: &str, v: String| {
            ui.label(k);
            ui.monospace(v);
            ui.end_row();
        };
        row("over the bound", format!("{} of {} frames", r.frames_over_bound, r.frames));
        // A block far over the bound next to the camera reaches huge factors.
        let worst =
            if r.worst_factor < 1e4 { format!("{:.2}", r.worst_factor) } else { format!("{:.2e}", r.worst_factor) };
        row("worst", format!("{worst} x delta"));
        row("triangles", r.triangles.to_string());
        row("blocks", r.blocks.to_string());
        row("tiles held", format!("{} ({:.0} of {} MB)", r.tiles_held, r.cache_mb, r.cache_budget_mb));
        row("tiles read", format!("{} ({:.0} MB)", r.tiles_loaded, r.read_mb));
        row("evicted", r.tiles_evicted.to_string());
        row("failed reads", r.tiles_failed.to_string());
        row("atlas", format!("{} layers, {} uploads", r.atlas_layers, r.uploaded_tiles));
        // Short rows: the panel's width is what a drag beside it must leave free.
        if let Some(e) = &r.errors {
            row("errors", format!("{} tiles, {:.2} M groups", e.tiles, e.groups as f64 / 1e6));
            let gpu = e.gpu_ms.map_or(String::new(), |ms| format!(", {ms:.1} ms"));
            row("read back", format!("{:.1} KB{gpu}", e.bytes_read_back as f64 / 1024.0));
            row("by errors", format!("{} blocks", r.blocks_bounded_by_errors));
        }
        // The name without the driver's details in brackets (it fits the panel).
        row("device", r.device.split(" (").next().unwrap_or_default().chars().take(24).collect());
        row("queues", r.queue_mode.clone());
        row("camera", r.camera.into());
        row("position", format!("{:.0}, {:.0}, {:.0}", r.position.x, r.position.y, r.position.z));
        row("above ground", format!("{:.0}", r.above_ground));
    });
    if let Some(p) = &r.place {
        map_section(ui, p, &mut c.go_to);
    }
    if let Some(l) = &r.legend {
        legend(ui, l);
    }
    ui.separator();
    delta_slider(ui, &mut c.delta);
    fog_slider(ui, &mut c.fog_density, r.fog_default);
    speed_slider(ui, &mut c.speed, r.speed_range);
    exaggeration_slider(ui, &mut c.exaggeration, "at once");
    ui.checkbox(&mut c.colour_by_lod, "LOD colours");
    if c.colour_by_lod {
        lod_legend(ui);
    }
    ui.horizontal(|ui| {
        if ui.button("Home").clicked() {
            c.go_home = true;
        }
        ui.small("F1 keys, H hides this panel");
    });
}
