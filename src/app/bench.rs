//! `vkterrain bench`: headless runs along a camera path (the paper's flyover, or a
//! 360-degree turn), writing per-frame figures, a summary, a plot like the paper's
//! Figure 8, and a Chrome trace of both activities.

use crate::app::cli::positive;
use crate::app::cli::{value_name, CommonArgs, Degraded, InputError, Interrupted, TextureArgs};
use crate::app::commands::{draw_thread, Session};
use crate::app::outputs::{median, percentile, plot_font, write_atomic};
use crate::app::paths::{path_camera, CameraPath};
use crate::draw::blocks::{BlocksRenderer, DrawStats, Shading, Target};
use crate::draw::frame::{FrameRequest, LodChoice};
use crate::draw::raycast::Raycast;
use crate::errors::activity::ErrorsActivity;
use crate::lod::block::DrawBlock;
use crate::lod::camera::Camera;
use crate::lod::gie::ErrorParams;
use crate::lod::traversal::{traverse, BlockCaches, LodSelect};
use crate::lod::view::near_plane;
use crate::trace::{Trace, DRAW_TID};
use clap::{Args, ValueEnum};
use glam::Vec3;
use serde_json::{json, Value};
use std::io::{IsTerminal, Write};
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant};

#[derive(Args, Debug)]
pub struct BenchArgs {
    #[command(flatten)]
    pub common: CommonArgs,
    #[command(flatten)]
    pub textures: TextureArgs,
    /// Camera path: `paper-flyover`, `rotate360`, or a file of poses, one a line:
    /// `cx cy cz lx ly lz` (camera position and look-at point in world units; blank lines
    /// and `#` comments skipped). With a file, frames = poses and --frames is ignored.
    #[arg(long, value_name = "PATH|FILE", default_value = "paper-flyover", value_parser = parse_path_arg)]
    pub path: PathArg,
    /// Frames, evenly spaced in simulated time along the path.
    #[arg(long, value_name = "N", default_value_t = 600, value_parser = crate::app::cli::at_least_one, allow_negative_numbers = true)]
    pub frames: u64,
    /// Output directory (frames.csv, summary.json, trace.json; plot.png for a terrain
    /// drawn in memory).
    #[arg(long, value_name = "DIR")]
    pub out: PathBuf,
    /// LOD selection of the main run.
    #[arg(long, value_enum, default_value_t = LodChoice::Error)]
    pub lod: LodChoice,
    /// Also run the same path with --lod full and --lod distance, and the rasterizer
    /// ceiling, and report the ratios.
    #[arg(long)]
    pub compare: bool,
    /// Skip the fidelity measurements (RMSE against --lod full at fixed views).
    #[arg(long)]
    pub no_fidelity: bool,
    /// Measure popping: read back every frame of the main run and of a --lod full run on
    /// the same path, take each frame's colour RMSE against the frame before, and report
    /// the main run's excess over the full run's (`popping` in summary.json and
    /// frames.csv). Reading frames back costs time, so compare fps without it.
    #[arg(long)]
    pub popping: bool,
    /// Where normals come from: the gradient map (default) or sixteen height fetches per
    /// pixel, to measure the pixel work side by side.
    #[arg(long, value_enum, default_value_t = crate::draw::blocks::NormalSource::GradientMap)]
    pub shading: crate::draw::blocks::NormalSource,
    /// How pixels are shaded: once each after a depth-only pass over the blocks
    /// (default), or as the blocks are drawn (forward), to measure the pixel work side by
    /// side.
    #[arg(long, value_enum, default_value_t = crate::draw::blocks::PixelPass::Deferred)]
    pub pixels: crate::draw::blocks::PixelPass,
    /// Blocks drawn by the ray-caster instead of as triangles: none, every
    /// other eligible block, every eligible one, or those estimated to cost less than
    /// their triangles (auto), to measure its cost beside the rasterizer's
    /// (`raycast_blocks` and `raycast_pixels` in frames.csv).
    #[arg(long, value_enum, default_value_t = crate::draw::raycast::Raycast::Off)]
    pub raycast: crate::draw::raycast::Raycast,
    /// Fail the run when a thread makes no progress for this many seconds.
    #[arg(long, value_name = "SECS", default_value = "10", value_parser = positive, allow_negative_numbers = true)]
    pub watchdog: f32,
    #[command(flatten)]
    pub streamed: crate::app::cli::StreamedOptions,
    /// Fault injection for tests: `errors-device-lost:G` (the errors thread loses the
    /// device at generation G), `draw-out-of-memory:F` (the draw thread runs out of
    /// device memory at frame F) or `interrupt-full:F` (Ctrl-C at frame F of the
    /// `--lod full` run that --compare and --popping add).
    #[arg(long, value_name = "FAULT:N", hide = true)]
    pub inject_fault: Option<String>,
}

/// A built-in camera path or a file of poses.
#[derive(Clone, Debug, PartialEq)]
pub enum PathArg {
    Builtin(CameraPath),
    File(PathBuf),
}

impl std::fmt::Display for PathArg {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            PathArg::Builtin(p) => write!(f, "{}", value_name(*p)),
            PathArg::File(p) => write!(f, "{}", p.display()),
        }
    }
}

fn parse_path_arg(s: &str) -> Result<PathArg, String> {
    match CameraPath::from_str(s, false) {
        Ok(p) => Ok(PathArg::Builtin(p)),
        Err(_) if s.is_empty() => Err("expected paper-flyover, rotate360 or a pose file".into()),
        Err(_) => Ok(PathArg::File(PathBuf::from(s))),
    }
}

/// Reads a pose file: one `cx cy cz lx ly lz` a line. Errors name the file and line.
pub fn read_poses(path: &Path) -> Result<Vec<(Vec3, Vec3)>, InputError> {
    crate::input::regular_file(path).map_err(|e| InputError(format!("--path {e}")))?;
    let text = std::fs::read_to_string(path).map_err(|e| InputError(format!("--path {}: {e}", path.display())))?;
    let mut poses = Vec::new();
    // A byte-order mark (as some editors save UTF-8) is not part of the first line.
    let text = text.strip_prefix('\u{feff}').unwrap_or(&text);
    for (n, line) in text.lines().enumerate() {
        let line = line.split('#').next().unwrap_or("").trim();
        if line.is_empty() {
            continue;
        }
        let bad =
            |what: &str| InputError(format!("{}:{}: {what} (expected: cx cy cz lx ly lz)", path.display(), n + 1));
        let v: Vec<f32> = line
            .split_whitespace()
            .map(|t| t.parse::<f32>().ok().filter(|v| v.is_finite()))
            .collect::<Option<_>>()
            .ok_or_else(|| bad("not six finite numbers"))?;
        if v.len() != 6 {
            return Err(bad(&format!("{} numbers", v.len())));
        }
        if v.iter().any(|c| c.abs() > crate::app::cli::MAX_WORLD) {
            return Err(bad(&format!("a coordinate beyond {:e} world units", crate::app::cli::MAX_WORLD)));
        }
        let (pos, look) = (Vec3::new(v[0], v[1], v[2]), Vec3::new(v[3], v[4], v[5]));
        if (look - pos).length() < 1e-6 {
            return Err(bad("the look-at point equals the position"));
        }
        poses.push((pos, look));
    }
    if poses.is_empty() {
        return Err(InputError(format!("--path {}: no poses", path.display())));
    }
    Ok(poses)
}

/// Writes poses in the format [`read_poses`] reads.
pub fn write_poses(poses: &[(Vec3, Vec3)]) -> String {
    let mut out = String::from("# vkterrain poses: cx cy cz lx ly lz (world units)\n");
    for (p, l) in poses {
        out += &format!("{} {} {} {} {} {}\n", p.x, p.y, p.z, l.x, l.y, l.z);
    }
    out
}

/// Writes a viewer's flight to `path` (`--record-path`), replaced whole, and says so.
pub fn record_poses(path: &std::path::Path, flight: &[(Vec3, Vec3)]) -> anyhow::Result<()> {
    let text = write_poses(flight);
    crate::app::outputs::write_atomic(path, |tmp| {
        std::fs::write(tmp, &text).map_err(|e| anyhow::anyhow!("{}: {e}", path.display()))
    })?;
    eprintln!("vkterrain: recorded {} poses to {}", flight.len(), path.display());
    Ok(())
}

/// One row of frames.csv.
#[derive(Clone, Debug, Default)]
struct Row {
    time_s: f64,
    frame_ms: f64,
    traverse_ms: f64,
    gpu_ms: Option<f64>,
    triangles: u64,
    draw_calls: u64,
    blocks: usize,
    error_generation: u64,
    error_age_frames: Option<u64>,
    error_update_ms: Option<f64>,
    /// Submit-to-done minus the frame's own GPU time: waiting behind other queue work.
    queue_wait_ms: Option<f64>,
    /// Blocks drawn part way between two LODs.
    morphing: usize,
    /// Selected blocks occlusion culling left undrawn (empty when it did not run or was
    /// skipped).
    occluded: Option<usize>,
    /// Parts occlusion culling hid and parts it tested (summary only).
    occluded_parts: Option<(usize, usize)>,
    /// Parts of drawn blocks left out as outside the frustum, and the drawn blocks' parts
    /// (summary only).
    outside_parts: (usize, usize),
    /// Colour RMSE against the previous frame (with --popping).
    temporal_rmse: Option<f64>,
    /// `temporal_rmse` minus the --lod full run's at the same frame (with --popping).
    popping: Option<f64>,
    /// Colour RMSE between this frame and the previous frame's blocks drawn from this
    /// frame's camera: the change due to LOD selection alone (with --popping).
    lod_change_rmse: Option<f64>,
    /// Share of the pixels compared for `lod_change_rmse` whose largest channel differs by
    /// more than 16 levels (the fidelity's threshold): a visible jump, which a sub-level
    /// change spread over many pixels (a morph step) does not make.
    lod_change_over16: Option<f64>,
    /// Blocks drawn by the ray-caster (only their outer ring is in `triangles`).
    raycast_blocks: u64,
    /// Pixels their boxes cover on screen (`draw::raycast::box_pixels`): the rays cast.
    raycast_pixels: f64,
    /// Parts left out of the blocks drawn as triangles: hidden by occlusion culling or
    /// outside the frustum (`DrawBlock::hidden_parts`).
    hidden_parts: u64,
    /// A block was drawn coarser than its error asks, its finer tile not held yet (never
    /// with the whole terrain in one image).
    over_bound: bool,
    /// The largest error / delta of a block drawn (terrains drawn from tiles).
    worst_factor: Option<f32>,
    /// Tiles the host cache held after the frame (terrains drawn from tiles).
    tiles_held: Option<usize>,
}

const CSV_HEADER: &str = "time_s,frame_ms,traverse_ms,gpu_ms,triangles,draw_calls,blocks,error_generation,\
                          error_age_frames,error_update_ms,queue_wait_ms,morphing,temporal_rmse,popping,lod_change_rmse,\
                          lod_change_over16,occluded,raycast_blocks,raycast_pixels,hidden_parts,over_bound,\
                          worst_factor,tiles_held";

fn opt<T: std::fmt::Display>(v: Option<T>) -> String {
    v.map_or(String::new(), |v| v.to_string())
}

impl Row {
    fn csv(&self) -> String {
        format!(
            "{:.4},{:.3},{:.3},{},{},{},{},{},{},{},{},{},{},{},{},{},{},{},{:.0},{},{},{},{}",
            self.time_s,
            self.frame_ms,
            self.traverse_ms,
            opt(self.gpu_ms.map(|v| format!("{v:.3}"))),
            self.triangles,
            self.draw_calls,
            self.blocks,
            self.error_generation,
            opt(self.error_age_frames),
            opt(self.error_update_ms.map(|v| format!("{v:.3}"))),
            opt(self.queue_wait_ms.map(|v| format!("{v:.3}"))),
            self.morphing,
            opt(self.temporal_rmse.map(|v| format!("{v:.4}"))),
            opt(self.popping.map(|v| format!("{v:.4}"))),
            opt(self.lod_change_rmse.map(|v| format!("{v:.4}"))),
            opt(self.lod_change_over16.map(|v| format!("{v:.7}"))),
            opt(self.occluded),
            self.raycast_blocks,
            self.raycast_pixels,
            self.hidden_parts,
            u8::from(self.over_bound),
            opt(self.worst_factor.map(|v| format!("{v:.4}"))),
            opt(self.tiles_held)
        )
    }
}

/// Resident set size in MiB (Linux).
pub fn rss_mib() -> Option<f64> {
    let statm = std::fs::read_to_string("/proc/self/statm").ok()?;
    let pages: f64 = statm.split_whitespace().nth(1)?.parse().ok()?;
    Some(pages * 4096.0 / (1024.0 * 1024.0))
}

/// Progress on stderr: a bar on a terminal, a line per 10% otherwise (a captured log
/// stays one line per step, not one line of carriage returns).
pub(crate) struct Progress {
    label: String,
    /// What is counted ("frames", "settings").
    unit: &'static str,
    total: u64,
    start: Instant,
    last: Instant,
    tty: bool,
    last_decile: u64,
}

impl Progress {
    /// A run's progress, named as the option that chose it ("error" alone would read as a
    /// failure).
    fn new(label: &str, total: u64) -> Self {
        let shown = match label {
            "error" | "full" | "distance" => format!("--lod {label}"),
            other => other.to_string(),
        };
        Progress::counting(&shown, total, "frames")
    }

    pub(crate) fn counting(label: &str, total: u64, unit: &'static str) -> Self {
        let now = Instant::now();
        Progress {
            label: label.into(),
            unit,
            total,
            start: now,
            last: now,
            tty: std::io::stderr().is_terminal(),
            last_decile: 0,
        }
    }

    pub(crate) fn tick(&mut self, done: u64) {
        let elapsed = self.start.elapsed();
        if elapsed < Duration::from_secs(2) && done < self.total {
            return; // only runs longer than a couple of seconds show progress
        }
        let rate = done as f64 / elapsed.as_secs_f64().max(1e-9);
        let per_s = if self.unit == "frames" { "fps".to_string() } else { format!("{} a second", self.unit) };
        if self.tty {
            if self.last.elapsed() < Duration::from_millis(200) && done < self.total {
                return;
            }
            self.last = Instant::now();
            let width = 30;
            let filled = (done * width / self.total.max(1)) as usize;
            eprint!(
                "\r{:>14} [{}{}] {done}/{} {}, {rate:.1} {per_s} ",
                self.label,
                "#".repeat(filled),
                ".".repeat(width as usize - filled),
                self.total,
                self.unit
            );
            if done >= self.total {
                eprintln!();
            }
        } else {
            let decile = done * 10 / self.total.max(1);
            if decile > self.last_decile {
                self.last_decile = decile;
                let percent = done * 100 / self.total.max(1);
                eprintln!("{}: {done}/{} {} ({percent}%), {rate:.1} {per_s}", self.label, self.total, self.unit);
            }
        }
        let _ = std::io::stderr().flush();
    }
}

/// Everything one run along the path produced.
struct Run {
    rows: Vec<Row>,
    /// Block lists per frame, kept for the rasterizer ceiling.
    blocks: Vec<Vec<DrawBlock>>,
    generations: Vec<u64>,
    update_gpu_ms: Vec<f64>,
    interrupted: bool,
    /// The untimed warm-up frame's time, waited for (ms).
    warmup_ms: Option<f64>,
    /// (frame, resident MiB) every 250 frames: a leak grows without bound, a cache levels off.
    rss: Vec<(u64, f64)>,
    /// Wall time from the first timed frame's start until every frame in flight finished
    /// (ms): what `avg_fps` divides by. The frames' own times leave out the GPU work of
    /// the last frames in flight, which a short run would count as free.
    wall_ms: Option<f64>,
    /// Drawn blocks whose error came from the errors activity's generation over the
    /// atlas, summed over the frames (terrains drawn from tiles).
    bounded_by_errors: u64,
}

/// Colour RMSE of each frame against the one before; frames may finish out of order
/// (one per slot), so they wait here until their predecessor has been seen.
#[derive(Default)]
struct TemporalDiff {
    next: usize,
    waiting: std::collections::BTreeMap<usize, Vec<u8>>,
    previous: Option<Vec<u8>>,
    /// Camera and blocks of the frames not yet compared.
    frames: std::collections::HashMap<usize, (Camera, Vec<DrawBlock>)>,
}

impl TemporalDiff {
    fn push(&mut self, row: usize, pixels: Vec<u8>, rows: &mut [Row]) {
        self.waiting.insert(row, pixels);
        while let Some(px) = self.waiting.remove(&self.next) {
            if let Some(prev) = &self.previous {
                rows[self.next].temporal_rmse = Some(image_difference(prev, &px).0);
            }
            self.previous = Some(px);
            self.next += 1;
        }
    }
}

/// Popping: per frame, the main run's change from the frame before minus the full
/// run's on the same path (what the camera's motion alone changes).
fn popping(main: &mut [Row], full: &[Row]) -> Value {
    let mut excess: Vec<f64> = Vec::new();
    for (m, f) in main.iter_mut().zip(full) {
        if let (Some(a), Some(b)) = (m.temporal_rmse, f.temporal_rmse) {
            m.popping = Some(a - b);
            excess.push(a - b);
        }
    }
    let n = excess.len();
    let (excess, mean) = sorted_with_mean(excess.into_iter());
    let (lod, _) = sorted_with_mean(main.iter().filter_map(|r| r.temporal_rmse));
    let (reference, _) = sorted_with_mean(full.iter().filter_map(|r| r.temporal_rmse));
    let (change, mean_change) = sorted_with_mean(main.iter().filter_map(|r| r.lod_change_rmse));
    let (over16, mean_over16) = sorted_with_mean(main.iter().filter_map(|r| r.lod_change_over16));
    let p99 = |s: &[f64]| (!s.is_empty()).then(|| percentile(s, 0.99));
    json!({
        "frame_pairs": n,
        "mean_excess": mean,
        "p99_excess": p99(&excess),
        "p99_temporal_rmse": (n > 0).then(|| percentile(&lod, 0.99)),
        "p99_temporal_rmse_full": (n > 0).then(|| percentile(&reference, 0.99)),
        "mean_lod_change_rmse": mean_change,
        "p99_lod_change_rmse": p99(&change),
        "max_lod_change_rmse": change.last(),
        "mean_lod_change_share_over16": mean_over16,
        "p99_lod_change_share_over16": p99(&over16),
        "max_lod_change_share_over16": over16.last(),
    })
}

/// The values sorted, and their mean (0 when there are none).
fn sorted_with_mean(values: impl Iterator<Item = f64>) -> (Vec<f64>, f64) {
    let mut v: Vec<f64> = values.collect();
    let mean = v.iter().sum::<f64>() / v.len().max(1) as f64;
    v.sort_by(f64::total_cmp);
    (v, mean)
}

struct Bench<'a> {
    s: &'a Session,
    args: &'a BenchArgs,
    renderer: BlocksRenderer,
    /// One offscreen target per frame in flight.
    targets: Vec<Target>,
    trace: Trace,
    stop: Arc<AtomicBool>,
    /// Frames drawn, for the watchdog.
    frames_done: Arc<AtomicU64>,
    size: (u32, u32),
    draw_oom_at: Option<u64>,
    /// Acts as Ctrl-C at this frame of the `--lod full` run (tests).
    interrupt_full_at: Option<u64>,
    /// Frames of the run: --frames, or the pose file's length.
    frames: u64,
    poses: Option<Vec<(Vec3, Vec3)>>,
}

impl Bench<'_> {
    /// Reads row `r`'s finished frame from `slot`. In an error-driven run it then draws
    /// row `r`'s blocks and the previous row's, both from row `r`'s camera, on a keyed
    /// background in the same slot: their difference where both show terrain is the LOD
    /// change alone (no motion, no blocks entering the frustum).
    fn camera(&self, i: u64) -> (Camera, f64) {
        match &self.poses {
            // Pose files carry no time: frames are 1/30 s apart.
            Some(p) => {
                let (pos, look) = p[i as usize];
                (
                    Camera::look_at(
                        pos,
                        look,
                        self.args.common.view.frustum.fovy,
                        self.size.0,
                        self.size.1,
                        near_plane(&self.s.hf),
                    ),
                    i as f64 / 30.0,
                )
            }
            None => {
                let path = match self.args.path {
                    PathArg::Builtin(p) => p,
                    PathArg::File(_) => CameraPath::PaperFlyover,
                };
                path_camera(&self.s.hf, &self.s.mm, path, i, self.frames, self.args.common.view.frustum.fovy, self.size)
            }
        }
    }

    /// Runs the whole path with one LOD mode (`ceiling`: replay given block lists with no
    /// traversal and no errors activity).
    fn run(
        &mut self,
        lod: LodChoice,
        activity: Option<&ErrorsActivity>,
        ceiling: Option<&[Vec<DrawBlock>]>,
        keep: bool,
    ) -> anyhow::Result<Run> {
        let label = match (ceiling, lod) {
            (Some(_), _) => "ceiling",
            (None, LodChoice::Error) => "error",
            (None, LodChoice::Full) => "full",
            (None, LodChoice::Distance) => "distance",
        };
        let mut progress = Progress::new(label, self.frames);
        let shading = self.args.textures.shade(Shading {
            normals: self.args.shading,
            pixels: self.args.pixels,
            raycast: self.args.raycast,
            ..Shading::default()
        });
        let mut run = Run {
            rows: Vec::new(),
            blocks: Vec::new(),
            generations: Vec::new(),
            update_gpu_ms: Vec::new(),
            interrupted: false,
            warmup_ms: None,
            rss: Vec::new(),
            wall_ms: None,
            bounded_by_errors: 0,
        };
        let mut timed_from: Option<Instant> = None;
        let mut draw = draw_thread(&self.args.common, self.trace.clone(), Some(&self.s.device))?;
        // Row of the frame pending in each offscreen slot.
        let mut pending: Vec<Option<usize>> = vec![None; self.targets.len()];
        let mut temporal = self.args.popping.then(TemporalDiff::default);
        let shared = self.s.device.queue_mode == crate::vk::QueueMode::Shared;
        let draw_track = self.trace.gpu_tid(false, shared);
        let trace = self.trace.clone();
        let fill = |row: &mut Row, stats: &DrawStats, frame: usize| {
            if let Some(t) = stats.gpu_ticks {
                trace.gpu_span(draw_track, label, t, json!({"frame": frame}));
            }
            if let Some((asked, got)) = stats.queue_lock {
                trace.complete(DRAW_TID, "wait (queue lock)", asked, got, json!({"frame": frame}));
            }
            if let Some((from, to)) = stats.waited {
                trace.complete(DRAW_TID, "wait (frame fence)", from, to, json!({"frame": frame}));
            }
            row.gpu_ms = stats.gpu_ms;
            row.queue_wait_ms = Some(stats.wait_ms);
            row.triangles = stats.triangles;
            row.raycast_blocks = stats.raycast_blocks;
            row.hidden_parts = stats.hidden_parts;
            row.draw_calls = stats.draw_calls;
        };
        // Step 0 is an untimed warm-up at the path's first pose, waited for before the
        // clock starts, so that no run pays for what only the first frame of a process or
        // a run does (llvmpipe compiles its shaders on first use, the errors activity's
        // first generation, the traversal's caches): frame 0 then follows it as frame 1
        // follows frame 0. Its time is `warmup_ms`.
        for step in 0..=self.frames {
            let warm_up = step == 0;
            let i = step.saturating_sub(1);
            if label == "full" && self.interrupt_full_at == Some(i) {
                self.stop.store(true, Ordering::SeqCst);
            }
            if self.stop.load(Ordering::SeqCst) {
                run.interrupted = true;
                break;
            }
            let (cam, time_s) = self.camera(i);
            let frame_start = Instant::now();
            if !warm_up {
                timed_from.get_or_insert(frame_start);
            }
            let mut row = Row { time_s, ..Row::default() };
            let replay = ceiling.map(|c| c.get(i as usize).map_or(&[][..], |b| &b[..]));
            if self.draw_oom_at == Some(i) {
                return Err(crate::vk::VkError::Call {
                    call: "vkAllocateMemory (injected fault)",
                    result: ash::vk::Result::ERROR_OUT_OF_DEVICE_MEMORY,
                    trace: String::new(),
                })
                .map_err(|e| anyhow::anyhow!("draw thread, frame {i}: {e}"));
            }
            // Frames in flight, as in the viewer: this frame goes into the next slot, and
            // what comes back is the slot's previous frame, finished.
            let slot = i as usize % self.targets.len();
            let request = FrameRequest { frame: i, cam: &cam, lod, delta: self.args.common.lod.delta, blocks: replay };
            let (renderer, targets, s, rows) = (&mut self.renderer, &self.targets, &self.s, &mut run.rows);
            let frame =
                draw.step(if replay.is_some() { None } else { activity }, s.lod_terrain(), request, |blocks| {
                    if let Some(diff) = &mut temporal {
                        // The slot's previous frame, finished: read it before it is drawn over.
                        if let (Some(stats), Some(r)) = (renderer.wait_frame(slot)?, pending[slot].take()) {
                            fill(&mut rows[r], &stats, r);
                            finish_temporal(renderer, &targets[slot], s, diff, slot, r, rows, &shading)?;
                        }
                        if lod == LodChoice::Error && replay.is_none() && !warm_up {
                            diff.frames.insert(rows.len(), (cam, blocks.to_vec()));
                        }
                    }
                    let t = Instant::now();
                    // Read back only where the pixels are compared (`--popping`): a
                    // window's frames are not copied either.
                    let read_back = temporal.is_some();
                    let done = renderer.submit_offscreen(
                        slot,
                        &s.hf,
                        &s.terrain,
                        &targets[slot],
                        &cam,
                        blocks,
                        &shading,
                        read_back,
                    )?;
                    Ok((done, t, Instant::now()))
                })?;
            let (done, submit_start, submit_end) = frame.submitted;
            if let Some(stats) = &done {
                draw.observe(stats);
            }
            if let Some(n) = frame.taken {
                let g = draw.feed.usable().expect("a generation was just taken");
                if let Some(ms) = g.gpu_ms {
                    run.update_gpu_ms.push(ms);
                }
                run.generations.push(n);
            }
            if let Some(tr) = &frame.traversal {
                row.traverse_ms = frame.traverse_ms;
                row.morphing = tr.morphing;
                let culled = tr.occlusion.filter(|o| o.skipped.is_none());
                row.occluded = culled.map(|o| o.hidden);
                row.occluded_parts = culled.map(|o| (o.hidden_parts, o.tested_parts));
                row.outside_parts =
                    (tr.frustum_parts, tr.blocks.len() * self.s.layout.all_parts().count_ones() as usize);
                if let Some(g) = draw.feed.usable() {
                    row.error_generation = g.number;
                    row.error_update_ms = g.gpu_ms;
                    row.error_age_frames = draw.feed.age_frames(i);
                }
            }
            let (blocks, _) = frame.into_parts();
            if shading.raycast != Raycast::Off {
                let choice = self.renderer.raycast_choice(&self.s.hf, &cam, shading.raycast);
                row.raycast_pixels = blocks.iter().filter(|b| choice.casts(b)).map(|b| choice.box_pixels(b)).sum();
            }
            if warm_up {
                self.renderer.wait_frame(slot)?;
                run.warmup_ms = Some(frame_start.elapsed().as_secs_f64() * 1e3);
                self.trace.complete(DRAW_TID, "warm-up (untimed)", frame_start, Instant::now(), json!({}));
                continue;
            }
            if let (Some(stats), Some(r)) = (done, pending[slot].take()) {
                fill(&mut run.rows[r], &stats, r);
            }
            pending[slot] = Some(run.rows.len());
            self.trace.instant(DRAW_TID, "submit (draw queue)", json!({"frame": i}));
            self.trace.complete(
                DRAW_TID,
                "wait + record + submit",
                submit_start,
                submit_end,
                json!({"frame": i, "blocks": blocks.len()}),
            );
            row.frame_ms = frame_start.elapsed().as_secs_f64() * 1e3;
            self.trace.complete(DRAW_TID, label, frame_start, Instant::now(), json!({"frame": i}));
            row.blocks = blocks.len();
            if keep {
                run.blocks.push(blocks);
            }
            run.rows.push(row);
            self.frames_done.fetch_add(1, Ordering::SeqCst);
            if (i + 1) % 250 == 0 {
                run.rss.extend(rss_mib().map(|m| (i + 1, m)));
            }
            progress.tick(i + 1);
        }
        for (slot, row) in pending.iter_mut().enumerate() {
            if let (Some(stats), Some(r)) = (self.renderer.wait_frame(slot)?, row.take()) {
                fill(&mut run.rows[r], &stats, r);
                if let Some(diff) = &mut temporal {
                    finish_temporal(
                        &mut self.renderer,
                        &self.targets[slot],
                        self.s,
                        diff,
                        slot,
                        r,
                        &mut run.rows,
                        &shading,
                    )?;
                }
            }
        }
        run.wall_ms = timed_from.map(|t| t.elapsed().as_secs_f64() * 1e3);
        if activity.is_some() {
            // Every block the traversal selects takes its error from the errors activity.
            run.bounded_by_errors = run.rows.iter().map(|r| r.blocks as u64).sum();
        }
        Ok(run)
    }
}

#[allow(clippy::too_many_arguments)]
fn finish_temporal(
    renderer: &mut BlocksRenderer,
    target: &Target,
    s: &Session,
    diff: &mut TemporalDiff,
    slot: usize,
    r: usize,
    rows: &mut [Row],
    shading: &Shading,
) -> anyhow::Result<()> {
    let pixels = target.pixels()?;
    if let (Some((cam, now)), Some((_, before))) =
        (diff.frames.get(&r), r.checked_sub(1).and_then(|p| diff.frames.get(&p)))
    {
        let keyed = Shading { sky: false, background: KEY_COLOUR, ..*shading };
        let mut images = Vec::new();
        for blocks in [now, before] {
            renderer.submit_offscreen(slot, &s.hf, &s.terrain, target, cam, blocks, &keyed, true)?;
            renderer.wait_frame(slot)?;
            images.push(target.pixels()?);
        }
        let (rmse, over16) = keyed_difference(&images[0], &images[1]);
        rows[r].lod_change_rmse = Some(rmse);
        rows[r].lod_change_over16 = Some(over16);
    }
    diff.frames.retain(|&k, _| k + 2 >= r);
    diff.push(r, pixels, rows);
    Ok(())
}

/// Median and 99th percentile of each frame's time minus the same frame's time in
/// `reference` (ms, frame by frame, as many as both have). Against the ceiling run, which
/// draws the same blocks with no traversal and no errors activity, this is what the
/// errors cost each frame: stalls show in its p99, while the path's own heavy stretches,
/// which slow both runs alike, do not. (A difference, not a ratio: frames with nothing
/// to draw take almost no time in the ceiling run.)
fn frame_time_excess(run: &[f64], reference: &[f64]) -> Option<(f64, f64)> {
    let mut d: Vec<f64> = run.iter().zip(reference).map(|(a, b)| a - b).collect();
    d.sort_by(|a, b| a.total_cmp(b));
    (!d.is_empty()).then(|| (percentile(&d, 0.5), percentile(&d, 0.99)))
}

/// The per-run figures of summary.json.
fn summarize(run: &Run) -> Value {
    let mut ms: Vec<f64> = run.rows.iter().map(|r| r.frame_ms).collect();
    ms.sort_by(|a, b| a.partial_cmp(b).unwrap());
    let total_s: f64 = run.wall_ms.unwrap_or_else(|| ms.iter().sum::<f64>()) / 1e3;
    let tris: u64 = run.rows.iter().map(|r| r.triangles).sum();
    let n = run.rows.len().max(1) as f64;
    let distinct = run.generations.len();
    let mut waits: Vec<f64> = run.rows.iter().filter_map(|r| r.queue_wait_ms).collect();
    waits.sort_by(|a, b| a.total_cmp(b));
    let p99_wait = (!waits.is_empty()).then(|| percentile(&waits, 0.99));
    // Occlusion: the share of selected blocks left undrawn, over the frames it ran on.
    let culled: Vec<(usize, usize)> = run.rows.iter().filter_map(|r| r.occluded.map(|o| (o, r.blocks))).collect();
    let occluded_share = (!culled.is_empty()).then(|| {
        let (hidden, drawn): (usize, usize) = culled.iter().fold((0, 0), |a, c| (a.0 + c.0, a.1 + c.1));
        hidden as f64 / (hidden + drawn).max(1) as f64
    });
    let parts = run.rows.iter().filter_map(|r| r.occluded_parts).fold((0, 0), |a, c| (a.0 + c.0, a.1 + c.1));
    let occluded_part_share = (parts.1 > 0).then(|| parts.0 as f64 / parts.1 as f64);
    let outside = run.rows.iter().fold((0, 0), |a, r| (a.0 + r.outside_parts.0, a.1 + r.outside_parts.1));
    let outside_part_share = (outside.1 > 0).then(|| outside.0 as f64 / outside.1 as f64);
    let morphing: usize = run.rows.iter().map(|r| r.morphing).sum();
    json!({
        "seconds": total_s,
        "mean_frame_ms": ms.iter().sum::<f64>() / n,
        "mean_morphing_blocks": morphing as f64 / n,
        // Of the blocks drawn a frame, those whose error came from the errors activity.
        "mean_blocks_bounded_by_errors": run.bounded_by_errors as f64 / n,
        "occluded_block_share": occluded_share,
        "occluded_part_share": occluded_part_share,
        "outside_part_share": outside_part_share,
        "occlusion_culled_frames": culled.len(),
        "warmup_ms": run.warmup_ms,
        "frames": run.rows.len(),
        "avg_fps": run.rows.len() as f64 / total_s.max(1e-9),
        "median_frame_ms": percentile(&ms, 0.5),
        "p99_frame_ms": percentile(&ms, 0.99),
        "mean_triangles": tris as f64 / n,
        "mtriangles_per_s": tris as f64 / total_s.max(1e-9) / 1e6,
        "mean_draw_calls": run.rows.iter().map(|r| r.draw_calls).sum::<u64>() as f64 / n,
        "median_traverse_ms": median(&run.rows.iter().map(|r| r.traverse_ms).collect::<Vec<_>>()),
        "median_gpu_ms": median(&run.rows.iter().filter_map(|r| r.gpu_ms).collect::<Vec<_>>()),
        "median_queue_wait_ms": median(&run.rows.iter().filter_map(|r| r.queue_wait_ms).collect::<Vec<_>>()),
        "p99_queue_wait_ms": p99_wait,
        "error_updates": distinct,
        "median_error_update_ms": median(&run.update_gpu_ms),
        "triangles_first_frame": run.rows.first().map(|r| r.triangles),
        "mean_raycast_blocks": run.rows.iter().map(|r| r.raycast_blocks).sum::<u64>() as f64 / n,
        "mean_raycast_pixels": run.rows.iter().map(|r| r.raycast_pixels).sum::<f64>() / n,
    })
}

/// `--compare`'s figures: each run's summary, the error run's frame rate and triangles
/// against full resolution's and the distance rings', and its frame times against the
/// ceiling's (the same blocks drawn with no selection), `again` being the ceiling run
/// twice: how far two identical runs drift apart on this machine.
fn compare_summary(main: &Run, full: &Run, distance: &Run, ceiling: &Run, again: &Run) -> Value {
    let (sm, sf, sd, sc) = (summarize(main), summarize(full), summarize(distance), summarize(ceiling));
    let ratio = |a: &Value, b: &Value, k: &str| a[k].as_f64().zip(b[k].as_f64()).map(|(x, y)| x / y.max(1e-12));
    let mut compare = json!({
        "fps_error_over_full": ratio(&sm, &sf, "avg_fps"),
        "fps_error_over_distance": ratio(&sm, &sd, "avg_fps"),
        "triangles_full_over_error": ratio(&sf, &sm, "mean_triangles"),
        "triangles_distance_over_error": ratio(&sd, &sm, "mean_triangles"),
        "share_of_ceiling_fps": ratio(&sm, &sc, "avg_fps"),
    });
    let ms = |run: &Run| run.rows.iter().map(|r| r.frame_ms).collect::<Vec<_>>();
    if let Some((median, p99)) = frame_time_excess(&ms(main), &ms(ceiling)) {
        compare["median_excess_over_ceiling_ms"] = json!(median);
        compare["p99_excess_over_ceiling_ms"] = json!(p99);
        let gap = frame_time_excess(&ms(again), &ms(ceiling)).map(|g| g.1);
        compare["p99_ceiling_gap_ms"] = json!(gap);
        // The stall target: a quarter of the ceiling's median frame, or 1.5x the gap
        // between two ceiling runs, the larger.
        let quarter = sc["median_frame_ms"].as_f64().map(|m| 0.25 * m);
        let target = quarter.zip(gap).map(|(q, g)| q.max(1.5 * g));
        compare["stall_target_ms"] = json!(target);
        compare["stall_target_met"] = json!(target.map(|t| p99 <= t));
    }
    (compare["error"], compare["full"], compare["distance"], compare["ceiling"]) = (sm, sf, sd, sc);
    compare
}

fn write_csv(path: &Path, rows: &[Row]) -> anyhow::Result<()> {
    let mut text = String::from(CSV_HEADER);
    text.push('\n');
    for r in rows {
        text.push_str(&r.csv());
        text.push('\n');
    }
    write_atomic(path, |tmp| std::fs::write(tmp, &text).map_err(|e| anyhow::anyhow!("{}: {e}", path.display())))
}

/// Frame rate and triangles against time, like the paper's Figure 8.
fn plot(path: &Path, rows: &[Row], title: &str) -> anyhow::Result<()> {
    use plotters::prelude::*;
    let have_font = plot_font();
    write_atomic(path, |tmp| {
        let root = BitMapBackend::new(tmp, (960, 640)).into_drawing_area();
        root.fill(&WHITE).map_err(|e| anyhow::anyhow!("plot: {e}"))?;
        let (upper, lower) = root.split_vertically(320);
        let t_max = rows.last().map_or(1.0, |r| r.time_s).max(1e-3);
        let fps: Vec<(f64, f64)> = rows.iter().map(|r| (r.time_s, 1000.0 / r.frame_ms.max(1e-6))).collect();
        let tris: Vec<(f64, f64)> = rows.iter().map(|r| (r.time_s, r.triangles as f64 / 1e6)).collect();
        for (area, data, label, color) in
            [(upper, fps, "frame rate (fps)", RED), (lower, tris, "triangles per frame (millions)", BLUE)]
        {
            let y_max = data.iter().map(|p| p.1).fold(0.0f64, f64::max).max(1e-6) * 1.1;
            let mut chart = ChartBuilder::on(&area);
            chart.margin(12);
            if have_font {
                chart
                    .caption(format!("{title}: {label}"), ("sans-serif", 18))
                    .x_label_area_size(30)
                    .y_label_area_size(50);
            }
            let mut chart =
                chart.build_cartesian_2d(0.0..t_max, 0.0..y_max).map_err(|e| anyhow::anyhow!("plot: {e}"))?;
            let mut mesh = chart.configure_mesh();
            if have_font {
                mesh.x_desc("simulated time (s)");
            } else {
                mesh.disable_x_mesh().disable_y_mesh();
            }
            mesh.draw().map_err(|e| anyhow::anyhow!("plot: {e}"))?;
            chart
                .draw_series(LineSeries::new(data, color.stroke_width(2)))
                .map_err(|e| anyhow::anyhow!("plot: {e}"))?;
        }
        root.present().map_err(|e| anyhow::anyhow!("plot: {e}"))?;
        Ok(())
    })
}

/// Background of the LOD-change images: pixels showing it in either image are left out.
const KEY_COLOUR: [f32; 3] = [1.0, 0.0, 1.0];

/// [`image_difference`] over the pixels that show terrain in both images.
fn keyed_difference(a: &[u8], b: &[u8]) -> (f64, f64) {
    let key = KEY_COLOUR.map(|c| (c * 255.0) as u8);
    difference(a, b, |p, q| p[..3] != key && q[..3] != key)
}

/// RMSE (8-bit) and the share of pixels with a channel off by more than 16 levels.
pub fn image_difference(a: &[u8], b: &[u8]) -> (f64, f64) {
    difference(a, b, |_, _| true)
}

/// [`image_difference`] over the RGBA pixels that `compared` accepts.
fn difference(a: &[u8], b: &[u8], compared: impl Fn(&[u8], &[u8]) -> bool) -> (f64, f64) {
    assert_eq!(a.len(), b.len(), "images of different sizes");
    let (mut se, mut over, mut n) = (0.0f64, 0usize, 0usize);
    for (p, q) in a.chunks(4).zip(b.chunks(4)) {
        if !compared(p, q) {
            continue;
        }
        let d = [0, 1, 2].map(|c| p[c] as i32 - q[c] as i32);
        se += d.iter().map(|d| (d * d) as f64).sum::<f64>();
        over += d.iter().any(|d| d.abs() > 16) as usize;
        n += 1;
    }
    ((se / (3 * n.max(1)) as f64).sqrt(), over as f64 / n.max(1) as f64)
}

/// A fault injected for tests (`--inject-fault`).
#[derive(Clone, Copy, Debug, PartialEq)]
enum Fault {
    /// The errors thread loses the device when it starts this generation (from 1).
    ErrorsDeviceLost(u64),
    /// The draw thread runs out of device memory at this frame of the main run.
    DrawOutOfMemory(u64),
    /// Ctrl-C at this frame of the `--lod full` run that --compare and --popping add.
    InterruptFull(u64),
}

/// Parses `--inject-fault FAULT:N`, refusing a fault that could never fire on a path of
/// `frames` frames (a test that injects one must see it happen).
fn parse_fault(arg: &str, frames: u64, full_run: bool) -> Result<Fault, InputError> {
    let bad = |why: &str| InputError(format!("--inject-fault {arg}: {why}"));
    let (kind, n) = arg.split_once(':').ok_or_else(|| bad("expected FAULT:N"))?;
    let n: u64 = n.parse().map_err(|_| bad("N is not a whole number"))?;
    let frame_in_path = |n: u64| {
        if n < frames {
            Ok(n)
        } else {
            Err(bad(&format!("the path's frames are 0 to {}", frames - 1)))
        }
    };
    match kind {
        "errors-device-lost" if n == 0 => Err(bad("generations are numbered from 1")),
        "errors-device-lost" => Ok(Fault::ErrorsDeviceLost(n)),
        "draw-out-of-memory" => frame_in_path(n).map(Fault::DrawOutOfMemory),
        "interrupt-full" if !full_run => Err(bad("there is no --lod full run without --compare or --popping")),
        "interrupt-full" => frame_in_path(n).map(Fault::InterruptFull),
        _ => Err(bad("unknown fault (errors-device-lost, draw-out-of-memory, interrupt-full)")),
    }
}

pub fn bench(args: &BenchArgs) -> anyhow::Result<()> {
    args.common.terrain.check_terrain()?;
    // Ctrl-C (or SIGTERM) stops the run cleanly; what was measured so far is written.
    // Installed first, so that a Ctrl-C during set-up still ends with a summary.
    let signals = super::signals::Stop::install();
    let stop = signals.flag().clone();
    if args.compare && args.lod != LodChoice::Error {
        // --compare makes the error run and compares the others with it.
        return Err(InputError(format!(
            "--compare runs every LOD selection itself (error, full, distance, the ceiling): drop --lod {}",
            if args.lod == LodChoice::Full { "full" } else { "distance" }
        ))
        .into());
    }
    crate::app::outputs::check_output_dir("--out", &args.out)?;
    let poses = match &args.path {
        PathArg::File(p) => Some(read_poses(p)?),
        PathArg::Builtin(_) => None,
    };
    let frames = poses.as_ref().map_or(args.frames, |p| p.len() as u64);
    let fault = match &args.inject_fault {
        Some(f) => Some(parse_fault(f, frames, args.compare || args.popping)?),
        None => None,
    };
    let device = crate::app::commands::open_device(&args.common.device, args.common.block)?;
    let max_side = || device.max_image_dimension_2d() as usize;
    // The bench polls its own stop handlers (`signals`), not a preparation's.
    if let Some((archive, _)) =
        crate::app::stream::streamed_archive(&args.common.terrain, args.streamed.from_tiles(), max_side)?
    {
        return bench_streamed(args, device, archive, poses, frames, fault, &signals);
    }
    let s = Session::with_device(device, &args.common.terrain, args.common.block, Some(&args.textures))?;
    crate::app::outputs::output_dir("--out", &args.out)?;
    let size = args.common.view.frustum.size.unwrap_or((640, 480));
    let threads =
        crate::draw::frame::traversal_threads(args.common.lod.traversal_threads, s.device.properties.device_type);
    s.check_viewport(size)?;
    let trace_path = args.out.join("trace.json");
    let trace = Trace::to_file(&trace_path).map_err(|e| anyhow::anyhow!("{}: {e}", trace_path.display()))?;
    match crate::vk::QueryPool::calibrate(&s.device)? {
        Some(clock) => trace.set_gpu_clock(clock, s.device.queue_mode == crate::vk::QueueMode::Shared),
        None => eprintln!("vkterrain: note: no timestamp queries: trace.json has no GPU tracks"),
    }
    let rss_start = rss_mib();
    let started = Instant::now();
    let activity = ErrorsActivity::start_with(
        &s.device,
        s.terrain.clone(),
        s.hf.clone(),
        s.layout,
        trace.clone(),
        args.common.error_pacing,
    )?;
    let frames_done = Arc::new(AtomicU64::new(0));
    let failed = Arc::new(AtomicBool::new(false));
    let mut bench = Bench {
        s: &s,
        args,
        renderer: BlocksRenderer::new(
            &s.device,
            &s.hf,
            &s.terrain,
            s.layout,
            crate::draw::blocks::COLOR_FORMAT,
            crate::draw::frame::FRAMES_IN_FLIGHT,
            args.common.sun.0,
        )?,
        targets: (0..crate::draw::frame::FRAMES_IN_FLIGHT)
            .map(|_| Target::new(&s.device, size.0, size.1))
            .collect::<crate::vk::VkResult<Vec<_>>>()?,
        trace: trace.clone(),
        stop: stop.clone(),
        frames_done: frames_done.clone(),
        size,
        draw_oom_at: None,
        interrupt_full_at: None,
        frames,
        poses,
    };
    match fault {
        Some(Fault::ErrorsDeviceLost(g)) => activity.inject_device_lost_at(g),
        Some(Fault::DrawOutOfMemory(f)) => bench.draw_oom_at = Some(f),
        Some(Fault::InterruptFull(f)) => bench.interrupt_full_at = Some(f),
        None => {}
    }

    let result = std::thread::scope(|scope| -> anyhow::Result<Value> {
        // Watchdog: the draw thread must finish a frame, and the errors thread a pending
        // generation, at least every `--watchdog` seconds.
        let limit = Duration::from_secs_f32(args.watchdog);
        let watch_stop = Arc::new(AtomicBool::new(false));
        {
            let (frames_done, failed, stop, watch_stop) =
                (frames_done.clone(), failed.clone(), stop.clone(), watch_stop.clone());
            let activity = &activity;
            scope.spawn(move || {
                let (mut last_f, mut last_f_at) = (0, Instant::now());
                let (mut last_g, mut last_g_at) = (0, Instant::now());
                while !watch_stop.load(Ordering::SeqCst) {
                    std::thread::sleep(Duration::from_millis(100));
                    let f = frames_done.load(Ordering::SeqCst);
                    if f != last_f {
                        (last_f, last_f_at) = (f, Instant::now());
                    }
                    let (busy, g) = activity.progress();
                    if g != last_g || !busy {
                        (last_g, last_g_at) = (g, Instant::now());
                    }
                    let stuck = if last_f_at.elapsed() > limit {
                        Some("draw thread")
                    } else if last_g_at.elapsed() > limit {
                        Some("errors activity")
                    } else {
                        None
                    };
                    if let Some(who) = stuck {
                        eprintln!("vkterrain: watchdog: the {who} made no progress for {} s", limit.as_secs_f64());
                        failed.store(true, Ordering::SeqCst);
                        stop.store(true, Ordering::SeqCst);
                        return;
                    }
                }
            });
        }
        let out = (|| -> anyhow::Result<Value> {
            let mut main =
                bench.run(args.lod, (args.lod == LodChoice::Error).then_some(&activity), None, args.compare)?;
            // A failure after the main run's last frame ends the run now, not after the
            // comparison runs.
            activity.check_failure()?;
            // A generation is recorded only when a newer one is observed.
            let increasing = main.generations.windows(2).all(|w| w[0] < w[1]);
            let mut summary = summarize(&main);
            summary["generations_strictly_increasing"] = json!(increasing);
            summary["most_generations_in_flight"] = json!(activity.most_in_flight());
            summary["rss_samples_mib"] = json!(main.rss);
            summary["interrupted"] = json!(main.interrupted);
            // Comparisons only from runs that went the whole path: a run stopped part way
            // (Ctrl-C, the watchdog) would make every ratio meaningless.
            let mut full = None;
            if (args.compare || args.popping) && !main.interrupted {
                // The comparison runs start once the errors activity has finished what the
                // main run asked of it, so that its last passes do not land in their frames.
                activity.wait_settled(Duration::from_secs_f32(args.watchdog))?;
                full = Some(bench.run(LodChoice::Full, None, None, false)?).filter(|r| !r.interrupted);
            }
            if let (true, Some(full)) = (args.popping, &full) {
                summary["popping"] = popping(&mut main.rows, &full.rows);
                summary["popping"]["morph"] = json!(args.common.lod.morph.on());
            }
            write_csv(&args.out.join("frames.csv"), &main.rows)?;
            if let (true, Some(full)) = (args.compare, full) {
                let distance = bench.run(LodChoice::Distance, None, None, false)?;
                let ceiling = bench.run(LodChoice::Full, None, Some(&main.blocks), false)?;
                // The same ceiling again: how far two identical runs drift apart frame by
                // frame on this machine, the floor under any stall figure.
                let again = bench.run(LodChoice::Full, None, Some(&main.blocks), false)?;
                // Frame by frame beside frames.csv: where the excess over the ceiling lies.
                write_csv(&args.out.join("ceiling.csv"), &ceiling.rows)?;
                if !distance.interrupted && !ceiling.interrupted && !again.interrupted {
                    summary["compare"] = compare_summary(&main, &full, &distance, &ceiling, &again);
                }
            }
            if !args.no_fidelity && !stop.load(Ordering::SeqCst) {
                summary["fidelity"] = fidelity(&mut bench, &activity)?;
            }
            plot(&args.out.join("plot.png"), &main.rows, &args.path.to_string())?;
            Ok(summary)
        })();
        watch_stop.store(true, Ordering::SeqCst);
        out
    });
    drop(bench);
    let started_generations = activity.started();
    let stopped = activity.stop();
    // The trace holds what was measured even when the run failed.
    let traced = trace.finish().map_err(|e| anyhow::anyhow!("{}: {e}", trace_path.display()));
    let mut summary = result?;
    // Any run stopped part way (the main run, or one that --compare or --popping added).
    if stop.load(Ordering::SeqCst) {
        summary["interrupted"] = json!(true);
    }
    stopped?;
    traced?;
    let secs = started.elapsed().as_secs_f64();
    summary["duration_s"] = json!(secs);
    summary["rss_start_mib"] = json!(rss_start);
    summary["rss_end_mib"] = json!(rss_mib());
    summary["path"] = json!(args.path.to_string());
    summary["lod"] = json!(format!("{:?}", args.lod).to_lowercase());
    summary["delta"] = json!(args.common.lod.delta);
    summary["size"] = json!([size.0, size.1]);
    summary["heightmap"] = json!(s.hf.source);
    summary["readback_bytes_per_update"] =
        json!(crate::lod::gie::BlockErrors::packed_len(s.layout.root_lod(), s.layout.roots) * 4 + 8);
    summary["geometry_bytes"] = json!(crate::app::commands::renderer_geometry_bytes(s.layout.k()));
    summary["heightfield_bytes"] = json!(s.hf.gpu_bytes());
    crate::app::outputs::TerrainFacts::of(&s.hf).merge_into(&mut summary);
    summary["queue_mode"] = json!(s.device.queue_mode.as_str());
    summary["device"] = json!(s.device.name);
    summary["validation"] = json!(s.device.instance.validation);
    // Destroy everything first, so that the object tracker's reports of leaked objects
    // (at vkDestroyDevice and vkDestroyInstance) are counted too.
    let messages = s.device.instance.messages.clone();
    drop(s);
    summary["validation_messages"] = json!(messages.count());
    summary["morph"] = json!(args.common.lod.morph.on());
    summary["error_mode"] = json!(args.common.error_mode.mode.as_str());
    // What was asked for: colour-by-LOD, wireframe, a device without clip distances and
    // cameras beyond `DEFERRED_MAX_SPACINGS` are shaded forward whatever this says.
    summary["pixels"] = json!(value_name(args.pixels));
    summary["shading"] = json!(value_name(args.shading));
    summary["validation_counted_after_device_destruction"] = json!(true);
    // Every sample is in memory: no frame lacks its data, none is over the bound, and no
    // tile is read, cached or uploaded (the keys a bench over tiles fills: one schema).
    summary["degraded"] = json!(false);
    summary["first_failure"] = Value::Null;
    summary["frames_over_bound"] = json!(0);
    summary["worst_factor"] = json!(1.0);
    summary["streamed"] = json!(false);
    summary["terrain"] = json!(args.common.terrain.name());
    summary["traversal_threads"] = json!(threads);
    summary["peak_resident_mb"] = json!(crate::app::outputs::peak_resident_mb());
    for tiles_only in ["cache_mb", "deferred_frames", "gpu", "stream", "warm_up"] {
        summary[tiles_only] = Value::Null;
    }
    let text = serde_json::to_string_pretty(&summary)?;
    let path = args.out.join("summary.json");
    write_atomic(&path, |tmp| std::fs::write(tmp, &text).map_err(|e| anyhow::anyhow!("{}: {e}", path.display())))?;
    crate::out!("{}", serde_json::to_string(&summary)?)?;
    if summary["generations_strictly_increasing"] == json!(false) {
        anyhow::bail!("generations observed out of order (see {})", path.display());
    }
    if failed.load(Ordering::SeqCst) {
        anyhow::bail!(
            "watchdog: a thread made no progress for {} s (partial results in {})",
            args.watchdog,
            args.out.display()
        );
    }
    if !stop.load(Ordering::SeqCst) {
        if let Some(Fault::ErrorsDeviceLost(g)) = fault {
            // Reached, it would have failed the run above.
            return Err(InputError(format!(
                "--inject-fault errors-device-lost:{g}: never reached, the run started {started_generations} generations"
            ))
            .into());
        }
    }
    let n = messages.count();
    if n > 0 {
        anyhow::bail!("{n} validation message(s)");
    }
    if stop.load(Ordering::SeqCst) {
        return Err(Interrupted::by(&signals, format!("partial results in {}", args.out.display())).into());
    }
    Ok(())
}

/// RMSE against the full-resolution image at three fixed views along the path, for
/// delta = 0.5, 1, 2, 5 (seed 004 section 5.3).
fn fidelity(bench: &mut Bench, activity: &ErrorsActivity) -> anyhow::Result<Value> {
    let mut out = Vec::new();
    for frac in [0.0f64, 0.5, 0.9] {
        let i = ((bench.frames - 1) as f64 * frac).round() as u64;
        let (cam, time_s) = bench.camera(i);
        let shading = Shading::default();
        let s = bench.s;
        let caches = BlockCaches::default();
        let full_blocks = traverse(&s.hf, &s.mm, &caches, &s.layout, &cam, LodSelect::Full).blocks;
        let (full, _) =
            bench.renderer.render_offscreen(&s.hf, &s.terrain, &bench.targets[0], &cam, &full_blocks, &shading)?;
        let g =
            activity.wait_for(ErrorParams::new(&cam, bench.args.common.error_mode.mode), Duration::from_secs(600))?;
        for delta in [0.5f32, 1.0, 2.0, 5.0] {
            let sel = LodSelect::errors(&g.errors, g.params.camera, delta, g.params.mode)
                .with_morph(bench.args.common.lod.morph.on());
            let blocks = traverse(&s.hf, &s.mm, &caches, &s.layout, &cam, sel).blocks;
            let (img, stats) =
                bench.renderer.render_offscreen(&s.hf, &s.terrain, &bench.targets[0], &cam, &blocks, &shading)?;
            let (rmse, share) = image_difference(&full, &img);
            out.push(json!({
                "time_s": time_s, "delta": delta, "rmse": rmse, "share_off_by_more_than_16": share,
                "triangles": stats.triangles, "full_triangles": full_blocks.len() as u64 * s.layout.triangles_per_block(),
            }));
        }
    }
    Ok(Value::Array(out))
}

/// `bench` over a terrain drawn streamed (SPEC section 8): the path's frames as a viewer
/// draws them, tiles read by the IO thread while the camera moves (a frame does not wait
/// for its tiles; those whose tiles had not arrived are counted over the bound), each
/// drawn from the atlas (not read back). Writes frames.csv and summary.json.
fn bench_streamed(
    args: &BenchArgs,
    device: Arc<crate::vk::Device>,
    archive: Arc<crate::input::archive::Archive>,
    poses: Option<Vec<(Vec3, Vec3)>>,
    frames: u64,
    fault: Option<Fault>,
    signals: &super::signals::Stop,
) -> anyhow::Result<()> {
    use crate::app::stream::{atlas_bound_streamer, streamed_grid, top_tiles};
    use crate::stream::traverse::View;
    let size = args.common.view.frustum.size.unwrap_or((640, 480));
    crate::app::cli::check_image_size(&device, "--size", size)?;
    crate::app::outputs::output_dir("--out", &args.out)?;
    // The three threads' work: each frame's selection and drawing, the IO thread's reads,
    // the atlas's uploads (CPU tracks; each frame's GPU time is in frames.csv).
    let trace_path = args.out.join("trace.json");
    let trace = Trace::to_file(&trace_path).map_err(|e| anyhow::anyhow!("{}: {e}", trace_path.display()))?;
    let grid = streamed_grid(&archive, &args.common.terrain.frame, args.common.block.k)?;
    let (cache_mb, gpu_mb) = (args.streamed.cache_mb(&archive.meta), args.streamed.gpu_mb(&archive.meta));
    let layers = device.properties.limits.max_image_array_layers;
    let mut streamer = atlas_bound_streamer(archive.clone(), grid, cache_mb, gpu_mb, layers, &trace)?;
    streamer.morph = crate::app::stream::morph_rule(args.common.lod.morph.setting);
    streamer.error_mode = args.common.error_mode.mode;
    streamer.refresh_at = args.common.refresh_at;
    streamer.lod = crate::app::stream::streamed_lod(args.lod);
    crate::app::stream::streamer_threads(&mut streamer, args.common.lod.traversal_threads, Some(&device))?;
    streamer.stop = Some(signals.flag().clone());
    let range = match top_tiles(&mut streamer, &archive.meta) {
        Err(_) if signals.requested() => {
            return Err(Interrupted::by(signals, "while the top tiles were read: nothing measured").into())
        }
        r => r?,
    };
    let [wx, wz] = grid.world_extent().map(|e| e as f32);
    let near = crate::lod::view::near_plane_for(grid.spacing[0].min(grid.spacing[1]) as f32);
    let ground = streamer.ground(f64::from(wx) * 0.5, f64::from(wz) * 0.5).unwrap_or(0.0) as f32;
    let terrain =
        crate::app::paths::PathTerrain { extent: (wx, wz), heights: range.world, centre_ground: ground, near };
    let fovy = args.common.view.frustum.fovy;
    let camera = |i: u64| -> (Vec3, Vec3, f64) {
        match &poses {
            Some(p) => (p[i as usize].0, p[i as usize].1, i as f64 / 30.0),
            None => {
                let path = match args.path {
                    PathArg::Builtin(p) => p,
                    PathArg::File(_) => CameraPath::PaperFlyover,
                };
                let (c, t) = crate::app::paths::path_camera_over(&terrain, path, i, frames, fovy, size);
                (c.position, c.position + c.forward, t)
            }
        }
    };
    let view = |i: u64| {
        let (p, l, _) = camera(i);
        View::look_at(p.as_dvec3(), l.as_dvec3(), fovy, size.0, size.1, near)
    };
    let messages = device.instance.messages.clone();
    let mut gpu = bench_frames(args, &device, &mut streamer, (gpu_mb, range, size), &archive.meta, (&trace, fault))?;
    let rss_start = rss_mib();
    let started_all = Instant::now();
    let path = StreamedPath {
        frames,
        grid: &grid,
        delta: args.common.lod.delta,
        view: &view,
        camera: &camera,
        trace: &trace,
        signals,
        fault,
    };
    let keep = args.compare || args.popping;
    let (mut run, selections, warm_up) =
        path.fly(&mut streamer, &mut gpu, (args.lod, None, keep, args.popping), "streamed")?;
    // The main run's drawing (the comparison runs draw on the same renderer).
    let (gpu_report, deferred_frames) = (gpu.report(), gpu.deferred_frames);
    let most_in_flight = gpu.errors_in_flight();
    let stats = streamer.stats.clone();
    // A frame never takes an older generation than the frame before.
    let mut taken: Vec<u64> = run.rows.iter().map(|r| r.error_generation).filter(|&g| g > 0).collect();
    taken.dedup();
    let increasing = taken.windows(2).all(|w| w[0] < w[1]);
    let shaded = gpu.errors_shaded();
    let readback_per_update = shaded.bytes_read_back / shaded.generations.max(1);
    let (compare, popped, fidelity) = path.after_the_run(args, (&mut streamer, &mut gpu), &mut run, &selections)?;
    // A failure after the last frame drawn fails the run too.
    if let Some(failure) = gpu.failure() {
        anyhow::bail!(failure);
    }
    let generations_shaded = gpu.errors_shaded().generations;
    // The in-memory bench's summary, then what frames from tiles add.
    let mut summary = summarize(&run);
    let streamed = json!({
        "streamed": true,
        "terrain": args.common.terrain.name(),
        "lod": format!("{:?}", args.lod).to_lowercase(),
        "shading": value_name(args.shading),
        "pixels": value_name(args.pixels),
        "deferred_frames": deferred_frames,
        "morph": args.common.lod.morph.on(),
        "error_mode": args.common.error_mode.mode.as_str(),
        "traversal_threads": streamer.threads(),
        "generations_strictly_increasing": increasing,
        "readback_bytes_per_update": readback_per_update,
        "geometry_bytes": crate::app::commands::renderer_geometry_bytes(grid.block_quads as u32 + 1),
        "heightfield_bytes": gpu.atlas_bytes(),
        "rss_start_mib": rss_start,
        "rss_end_mib": rss_mib(),
        "rss_samples_mib": run.rss,
        "frames_over_bound": stats.frames_over_bound,
        "worst_factor": stats.worst_factor,
        "delta": args.common.lod.delta,
        "size": [size.0, size.1],
        "cache_mb": cache_mb,
        "stream": stats,
        "warm_up": { "frames": warm_up.frames, "tiles_loaded": warm_up.tiles_loaded, "bytes_read": warm_up.bytes_read },
        "gpu": gpu_report,
        "device": device.name,
        "queue_mode": device.queue_mode.as_str(),
        "most_generations_in_flight": most_in_flight,
        "validation": device.instance.validation,
        "validation_messages": device.instance.validation_messages(),
        "path": args.path.to_string(),
        "heightmap": args.common.terrain.heightmap,
        "duration_s": started_all.elapsed().as_secs_f64(),
        "peak_resident_mb": crate::app::outputs::peak_resident_mb(),
        "interrupted": signals.requested(),
        "degraded": streamer.first_failure.is_some(),
        "first_failure": streamer.first_failure,
    });
    if let (Some(all), Value::Object(more)) = (summary.as_object_mut(), streamed) {
        all.extend(more);
    }
    if let Some(c) = compare {
        summary["compare"] = c;
    }
    if let Some(p) = popped {
        summary["popping"] = p;
    }
    if let Some(f) = fidelity {
        summary["fidelity"] = f;
    }
    let streamer_failure = streamer.first_failure.clone();
    crate::app::outputs::TerrainFacts::of_archive(&archive.meta, &args.common.terrain.frame).merge_into(&mut summary);
    drop(gpu);
    drop(device);
    drop(streamer); // joins the IO thread: its last read is in the trace
                    // Counted with every object destroyed, as in memory: the object tracker's reports of
                    // leaked objects (at vkDestroyDevice and vkDestroyInstance) count too.
    summary["validation_messages"] = json!(messages.count());
    summary["validation_counted_after_device_destruction"] = json!(true);
    trace.finish().map_err(|e| anyhow::anyhow!("{}: {e}", trace_path.display()))?;
    write_csv(&args.out.join("frames.csv"), &run.rows)?;
    plot(&args.out.join("plot.png"), &run.rows, &args.path.to_string())?;
    let text = serde_json::to_string_pretty(&summary)?;
    write_atomic(&args.out.join("summary.json"), |tmp| Ok(std::fs::write(tmp, &text)?))?;
    crate::out!("{text}")?;
    crate::app::cli::check_messages(&messages)?;
    if signals.requested() {
        return Err(Interrupted::by(signals, format!("partial results in {}", args.out.display())).into());
    }
    if let Some(Fault::ErrorsDeviceLost(g)) = fault {
        // Reached, it would have failed the run above.
        return Err(InputError(format!(
            "--inject-fault errors-device-lost:{g}: never reached, the run started {generations_shaded} generations"
        ))
        .into());
    }
    if let Some(failure) = &streamer_failure {
        return Err(
            Degraded(format!("tiles could not be read (first: {failure}); frames drawn without their data")).into()
        );
    }
    Ok(())
}

/// The GPU side of a bench over tiles (the archive's `m`): an atlas of `gpu_mb` MB
/// attached to `streamer` and frames of `size`, set as `args` asks (shading, textures,
/// sun, occlusion), drawn and not read back (as in memory), with `fault` injected.
fn bench_frames(
    args: &BenchArgs,
    device: &Arc<crate::vk::Device>,
    streamer: &mut crate::stream::streamer::Streamer,
    (gpu_mb, range, size): (u32, crate::draw::streamed::HeightRange, (u32, u32)),
    m: &crate::input::archive::Meta,
    (trace, fault): (&Trace, Option<Fault>),
) -> anyhow::Result<crate::app::stream::GpuFrames> {
    let mut gpu = crate::app::stream::GpuFrames::new(device.clone(), streamer, gpu_mb, range, size, trace)?;
    gpu.pace_errors(&args.common);
    gpu.set_normals(args.shading);
    gpu.set_pixels(args.pixels);
    gpu.set_textures(&args.textures.load_over(&m.georef, (m.width, m.height))?, &args.textures)?;
    gpu.sun(args.common.sun.0)?;
    gpu.occlusion = args.common.occlusion != Some(crate::app::cli::OnOff::Off);
    gpu.raycast = args.raycast;
    gpu.read_back = false;
    if let Some(Fault::ErrorsDeviceLost(n)) = fault {
        gpu.inject_device_lost_at(n);
    }
    Ok(gpu)
}

/// A bench's path over a terrain drawn from tiles: what each of its runs flies.
struct StreamedPath<'a> {
    frames: u64,
    grid: &'a crate::stream::Grid,
    delta: f32,
    view: &'a dyn Fn(u64) -> crate::stream::traverse::View,
    camera: &'a dyn Fn(u64) -> (Vec3, Vec3, f64),
    trace: &'a Trace,
    signals: &'a crate::app::signals::Stop,
    /// A fault injected for tests (`--inject-fault`): the draw fails, or a stop is asked for.
    fault: Option<Fault>,
}

/// How a [`StreamedPath`] run chooses its blocks: the LOD rule, or selections to draw
/// again with none made; whether it keeps its selections; whether it measures popping.
type FlyHow<'a> = (LodChoice, Option<&'a [crate::stream::traverse::Selection]>, bool, bool);

impl StreamedPath<'_> {
    /// What `args` asks for after the main `run` (its `selections` kept): the `--lod full`
    /// run that `--compare` and `--popping` compare with, the popping figures, the
    /// comparison runs (the rings, the ceiling twice: `ceiling.csv`) and the fidelity.
    /// Comparisons only from runs that went the whole path, as in memory.
    fn after_the_run(
        &self,
        args: &BenchArgs,
        (streamer, gpu): (&mut crate::stream::streamer::Streamer, &mut crate::app::stream::GpuFrames),
        run: &mut Run,
        selections: &[crate::stream::traverse::Selection],
    ) -> anyhow::Result<(Option<Value>, Option<Value>, Option<Value>)> {
        let keep = args.compare || args.popping;
        let full = match keep && !run.interrupted {
            true => Some(self.fly(streamer, gpu, (LodChoice::Full, None, false, args.popping), "full")?.0),
            false => None,
        }
        .filter(|r| !r.interrupted);
        let popped = match (args.popping, &full) {
            (true, Some(full)) => {
                let mut p = popping(&mut run.rows, &full.rows);
                p["morph"] = json!(args.common.lod.morph.on());
                Some(p)
            }
            _ => None,
        };
        let compare = match (args.compare, full) {
            (true, Some(full)) => {
                let (distance, _, _) =
                    self.fly(streamer, gpu, (LodChoice::Distance, None, false, false), "distance")?;
                let replay = (LodChoice::Error, Some(selections), false, false);
                let (ceiling, _, _) = self.fly(streamer, gpu, replay, "ceiling")?;
                let (again, _, _) = self.fly(streamer, gpu, replay, "ceiling again")?;
                write_csv(&args.out.join("ceiling.csv"), &ceiling.rows)?;
                let whole = [&full, &distance, &ceiling, &again].iter().all(|r| !r.interrupted);
                whole.then(|| compare_summary(run, &full, &distance, &ceiling, &again))
            }
            _ => None,
        };
        let fidelity = match !args.no_fidelity && !self.signals.requested() {
            true => Some(self.fidelity(streamer, gpu)?),
            false => None,
        };
        Ok((compare, popped, fidelity))
    }

    /// As in memory ([`fidelity`]): RMSE against the full-resolution image at three fixed
    /// views along the path, for delta = 0.5, 1, 2, 5, each frame settled (its tiles read,
    /// its errors from the errors activity).
    fn fidelity(
        &self,
        streamer: &mut crate::stream::streamer::Streamer,
        gpu: &mut crate::app::stream::GpuFrames,
    ) -> anyhow::Result<Value> {
        let (lod, read_back) = (streamer.lod, gpu.read_back);
        gpu.read_back = true;
        let mut out = Vec::new();
        for frac in [0.0f64, 0.5, 0.9] {
            let i = ((self.frames - 1) as f64 * frac).round() as u64;
            let (view, time_s) = ((self.view)(i), (self.camera)(i).2);
            streamer.lod = crate::app::stream::streamed_lod(LodChoice::Full);
            let (_, sel) = crate::app::stream::settle(streamer, |_| view, 1.0);
            gpu.draw(streamer, self.grid, &view, &sel, None)?;
            let (full, full_triangles) = (std::mem::take(&mut gpu.last), gpu.drawn.triangles);
            streamer.lod = crate::app::stream::streamed_lod(LodChoice::Error);
            for delta in [0.5f32, 1.0, 2.0, 5.0] {
                let (_, sel) = crate::app::stream::settle(streamer, |_| view, delta);
                gpu.draw(streamer, self.grid, &view, &sel, None)?;
                let (rmse, share) = image_difference(&full, &gpu.last);
                out.push(json!({
                    "time_s": time_s, "delta": delta, "rmse": rmse, "share_off_by_more_than_16": share,
                    "triangles": gpu.drawn.triangles, "full_triangles": full_triangles,
                }));
            }
        }
        (streamer.lod, gpu.read_back) = (lod, read_back);
        Ok(Value::Array(out))
    }

    /// One run along the path with the blocks `lod` chooses, or `replay`'s selections
    /// drawn again with none made (the ceiling); its frames, rows in the one frames.csv
    /// schema every bench writes (what frames from tiles do not have, such as error
    /// generations and GPU timestamps, left empty or 0), its selections when `keep`, and
    /// what its first view read. With `pop`, as in memory: each frame read back and
    /// compared with the one before (`temporal_rmse`), and, with `keep`, the frame's
    /// blocks against the previous frame's drawn from this frame's camera on a keyed
    /// background (`lod_change_rmse`).
    fn fly(
        &self,
        streamer: &mut crate::stream::streamer::Streamer,
        gpu: &mut crate::app::stream::GpuFrames,
        (lod, replay, keep, pop): FlyHow<'_>,
        name: &str,
    ) -> anyhow::Result<(Run, Vec<crate::stream::traverse::Selection>, crate::stream::streamer::StreamStats)> {
        streamer.lod = crate::app::stream::streamed_lod(lod);
        gpu.read_back = pop;
        // A replay draws what culling left of the run it replays, with no sweep of its own.
        let occlusion = gpu.occlusion;
        gpu.occlusion &= replay.is_none();
        gpu.new_run();
        // As a viewer would: the first view's tiles are read before the run (for every
        // run: `--lod full` needs other tiles than the bound's); the run's own figures
        // from here, what the first view read returned apart.
        let (_, first) = crate::app::stream::settle(streamer, |_| (self.view)(0), self.delta);
        let warm_up = std::mem::replace(
            &mut streamer.stats,
            crate::stream::streamer::StreamStats { worst_factor: 1.0, ..Default::default() },
        );
        // One untimed frame first, as every in-memory run begins (`warmup_ms`).
        let warming = Instant::now();
        gpu.draw(streamer, self.grid, &(self.view)(0), replay.map_or(&first, |r| &r[0]), None)?;
        let warmup_ms = Some(warming.elapsed().as_secs_f64() * 1e3);
        let mut progress = Progress::new(name, self.frames);
        let (mut rows, mut kept) = (Vec::new(), Vec::new());
        let (mut previous_pixels, mut previous_sel): (Option<Vec<u8>>, Option<crate::stream::traverse::Selection>) =
            (None, None);
        let started = Instant::now();
        // The errors activity's generations shaded during the run and their GPU times;
        // the one each frame took and the frame that first took it.
        let shaded_before = gpu.errors_shaded();
        let (mut taken, mut taken_at, mut bounded_by_errors) = (0u64, 0u64, 0u64);
        for i in 0..self.frames {
            if name == "full" && self.fault == Some(Fault::InterruptFull(i)) {
                self.signals.flag().store(true, std::sync::atomic::Ordering::SeqCst);
            }
            if self.signals.requested() {
                break;
            }
            if name == "streamed" && self.fault == Some(Fault::DrawOutOfMemory(i)) {
                return Err(crate::vk::VkError::Call {
                    call: "vkAllocateMemory (injected fault)",
                    result: ash::vk::Result::ERROR_OUT_OF_DEVICE_MEMORY,
                    trace: String::new(),
                })
                .map_err(|e| anyhow::anyhow!("draw thread, frame {i}: {e}"));
            }
            let t0 = Instant::now();
            let v = (self.view)(i);
            let sel = match replay {
                Some(r) => r[i as usize].clone(),
                None => {
                    // The camera half a second ahead along the path: its tiles are asked
                    // for next.
                    let ahead = (self.view)((i + 15).min(self.frames - 1));
                    streamer.frame(&v, Some(&ahead), self.delta, 0.5)
                }
            };
            let t1 = Instant::now();
            self.trace.complete(DRAW_TID, "select (traversal over held tiles)", t0, t1, json!({"frame": i}));
            gpu.draw(streamer, self.grid, &v, &sel, None)?;
            let culled = gpu.last_occlusion.filter(|o| o.skipped.is_none());
            // What culling hid stays hidden when the frame is drawn again (the ceiling
            // draws the run's own blocks with no selection work).
            let masks = std::mem::take(&mut gpu.culled_masks);
            self.trace.complete(
                DRAW_TID,
                "frame",
                t0,
                Instant::now(),
                json!({"frame": i, "over_bound": sel.over_bound}),
            );
            self.trace.counter("tiles held", streamer.cache.len() as u64);
            let mut row = Row {
                time_s: (self.camera)(i).2,
                frame_ms: t0.elapsed().as_secs_f64() * 1e3,
                traverse_ms: (t1 - t0).as_secs_f64() * 1e3,
                triangles: gpu.drawn.triangles,
                draw_calls: gpu.drawn.draw_calls,
                blocks: gpu.drawn.blocks,
                gpu_ms: gpu.drawn.gpu_ms,
                morphing: sel.morphing,
                hidden_parts: gpu.drawn.hidden_parts,
                raycast_blocks: gpu.drawn.raycast_blocks,
                raycast_pixels: gpu.drawn.raycast_pixels,
                over_bound: sel.over_bound > 0,
                worst_factor: Some(sel.worst_factor),
                tiles_held: Some(streamer.cache.len()),
                error_generation: sel.errors_generation,
                error_update_ms: sel.errors_gpu_ms,
                occluded: culled.map(|o| o.hidden),
                occluded_parts: culled.map(|o| (o.hidden_parts, o.tested_parts)),
                ..Row::default()
            };
            bounded_by_errors += sel.drawn_bounded_by().0 as u64;
            if sel.errors_generation > 0 {
                if taken != sel.errors_generation {
                    (taken, taken_at) = (sel.errors_generation, i);
                }
                row.error_age_frames = Some(i - taken_at);
            }
            if pop {
                let pixels = std::mem::take(&mut gpu.last);
                row.temporal_rmse = previous_pixels.as_ref().map(|p| image_difference(p, &pixels).0);
                previous_pixels = Some(pixels);
                if let Some(before) = previous_sel.as_ref().filter(|_| keep) {
                    let background = gpu.background.replace(KEY_COLOUR);
                    gpu.draw(streamer, self.grid, &v, &sel, None)?;
                    let now = std::mem::take(&mut gpu.last);
                    gpu.draw(streamer, self.grid, &v, before, None)?;
                    gpu.background = background;
                    let (rmse, over16) = keyed_difference(&now, &gpu.last);
                    (row.lod_change_rmse, row.lod_change_over16) = (Some(rmse), Some(over16));
                }
                previous_sel = keep.then(|| sel.clone());
            }
            rows.push(row);
            if keep {
                let mut sel = sel;
                for (b, m) in sel.stitched.iter_mut().zip(&masks) {
                    b.hidden_parts |= m;
                }
                kept.push(sel);
            }
            progress.tick(i + 1);
        }
        gpu.occlusion = occlusion;
        let shaded = gpu.errors_shaded();
        let mut update_gpu_ms = shaded.gpu_ms;
        let update_gpu_ms = update_gpu_ms.split_off(shaded_before.gpu_ms.len().min(update_gpu_ms.len()));
        let run = Run {
            rows,
            blocks: Vec::new(),
            // Counted as generations: `error_updates` is how many the run shaded.
            generations: (shaded_before.generations..shaded.generations).collect(),
            update_gpu_ms,
            bounded_by_errors,
            interrupted: self.signals.requested(),
            warmup_ms,
            rss: Vec::new(),
            wall_ms: Some(started.elapsed().as_secs_f64() * 1e3),
        };
        Ok((run, kept, warm_up))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A pose file saved with a byte-order mark reads as without one; a mark anywhere
    /// else is still refused, naming the line.
    #[test]
    fn pose_files_may_start_with_a_byte_order_mark() {
        let dir = std::env::temp_dir().join(format!("vkterrain-poses-bom-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let path = dir.join("p.txt");
        std::fs::write(&path, "\u{feff}1 2 3 4 5 6\n7 8 9 1 2 3\n").unwrap();
        let read = read_poses(&path);
        std::fs::write(&path, "1 2 3 4 5 6\n\u{feff}7 8 9 1 2 3\n").unwrap();
        let inner = read_poses(&path);
        std::fs::remove_dir_all(&dir).unwrap();
        let poses = read.unwrap();
        assert_eq!(
            poses,
            [
                (Vec3::new(1.0, 2.0, 3.0), Vec3::new(4.0, 5.0, 6.0)),
                (Vec3::new(7.0, 8.0, 9.0), Vec3::new(1.0, 2.0, 3.0))
            ]
        );
        assert!(inner.unwrap_err().0.contains("p.txt:2"));
    }

    /// Keyed pixels are left out; the RMSE is over the rest, and only a channel more
    /// than 16 levels off counts as a visible jump (16 itself does not).
    #[test]
    fn keyed_difference_counts_visible_jumps_only() {
        let key = KEY_COLOUR.map(|c| (c * 255.0) as u8);
        let px = |r: u8, g: u8, b: u8| [r, g, b, 255];
        let a: Vec<u8> = [px(10, 10, 10), px(10, 10, 10), px(10, 10, 10), px(key[0], key[1], key[2])].concat();
        let b: Vec<u8> = [px(10, 10, 10), px(26, 10, 10), px(10, 10, 27), px(200, 0, 0)].concat();
        let (rmse, over) = keyed_difference(&a, &b);
        assert!((rmse - ((16.0f64 * 16.0 + 17.0 * 17.0) / 9.0).sqrt()).abs() < 1e-9, "{rmse}");
        assert!((over - 1.0 / 3.0).abs() < 1e-12, "{over}");
    }

    /// A path whose second half is twice as heavy slows both runs alike: the excess stays
    /// as it was. Stalled frames (2 in 100) show in the p99, not the median.
    #[test]
    fn frame_time_excess_sees_stalls_not_the_path() {
        let ceiling: Vec<f64> = (0..100).map(|i| if i < 50 { 10.0 } else { 20.0 }).collect();
        let same: Vec<f64> = ceiling.iter().map(|c| c + 2.0).collect();
        let (m, p) = frame_time_excess(&same, &ceiling).unwrap();
        assert!((m - 2.0).abs() < 1e-9 && (p - 2.0).abs() < 1e-9, "{m} {p}");
        let mut stalled = same.clone();
        stalled[70] = 100.0;
        stalled[80] = 100.0;
        let (m, p) = frame_time_excess(&stalled, &ceiling).unwrap();
        assert!((m - 2.0).abs() < 1e-9, "{m}");
        assert!((p - 80.0).abs() < 1e-9, "{p}");
        assert_eq!(frame_time_excess(&[], &ceiling), None);
    }
}
