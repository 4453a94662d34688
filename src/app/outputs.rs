//! What the commands write: files replaced atomically (no partial file is ever left under
//! the name asked for), output options checked before any work, PNGs and plots.

use crate::app::cli::InputError;
use std::path::Path;

/// Writes `bytes` to `path` through a temporary file, so that no partial file is left.
pub fn write_atomic(path: &Path, write: impl FnOnce(&Path) -> anyhow::Result<()>) -> anyhow::Result<()> {
    // Through a symbolic link to the file it names (as `cp` does), never onto a
    // directory, pipe or device.
    let path = output_target(path).map_err(|e| anyhow::anyhow!(e))?;
    // A name of this process's own: two runs writing the same file must not share it
    // (the last rename wins, and neither fails).
    // It keeps the extension, so that writers that choose the format by it (plotters,
    // image) still can.
    let ext = path.extension().map_or(String::new(), |e| format!(".{}", e.to_string_lossy()));
    let tmp = path.with_extension(format!("{}.partial{ext}", std::process::id()));
    let written =
        write(&tmp).and_then(|()| std::fs::rename(&tmp, &path).map_err(|e| anyhow::anyhow!("{}: {e}", path.display())));
    if written.is_err() {
        let _ = std::fs::remove_file(&tmp);
    }
    written
}

/// An output directory option (`bench --out`, `quality --out`): an existing file there is
/// refused naming the option, and the directory is made (with its parents) before any
/// work, so that a long run does not fail at its end.
pub fn output_dir(option: &str, dir: &Path) -> Result<(), InputError> {
    check_output_dir(option, dir)?;
    std::fs::create_dir_all(dir).map_err(|e| InputError(format!("{option} {}: {e}", dir.display())))
}

/// [`output_dir`]'s check alone, for a command that refuses other options first and
/// makes nothing until they pass.
pub fn check_output_dir(option: &str, dir: &Path) -> Result<(), InputError> {
    if dir.exists() && !dir.is_dir() {
        return Err(InputError(format!("{option} {}: exists and is not a directory", dir.display())));
    }
    Ok(())
}

/// Checks a command's output options before any work: each names a file that can be
/// written ([`output_target`]), no two name the same file, and none names an input.
pub fn check_outputs(outputs: &[(&str, Option<&Path>)], inputs: &[(&str, Option<&Path>)]) -> Result<(), InputError> {
    // Compared by the canonical directory and the file name (the file may not exist yet).
    let key = |p: &Path| {
        let dir = p.parent().filter(|d| !d.as_os_str().is_empty()).unwrap_or(Path::new("."));
        dir.canonicalize().map_or(p.to_path_buf(), |d| d.join(p.file_name().unwrap_or_default()))
    };
    let mut seen: Vec<(&str, std::path::PathBuf)> = Vec::new();
    for &(opt, input) in inputs {
        if let Some(p) = input {
            if let Ok(real) = p.canonicalize() {
                seen.push((opt, real));
            }
        }
    }
    for &(opt, output) in outputs {
        let Some(p) = output else { continue };
        let target = output_target(p).map_err(|e| InputError(format!("{opt} {e}")))?;
        let k = key(&target);
        if let Some((other, _)) = seen.iter().find(|(_, t)| *t == k) {
            return Err(InputError(format!("{opt} {}: the same file as {other}", p.display())));
        }
        seen.push((opt, k));
    }
    Ok(())
}

/// The file an output option writes: `path` itself, or the file a symbolic link at
/// `path` points to. An error (naming the path) when that is a directory, a pipe or a
/// device, or when its directory does not exist. Checked when options are read, so that
/// a long run does not fail at its end, and again when writing.
pub fn output_target(path: &Path) -> Result<std::path::PathBuf, String> {
    if path.as_os_str().to_string_lossy().ends_with('/') || path.file_name().is_none() {
        return Err(format!("{}: names a directory, not a file", path.display()));
    }
    let mut target = path.to_path_buf();
    for _ in 0..32 {
        match std::fs::symlink_metadata(&target) {
            Ok(m) if m.file_type().is_symlink() => {
                let link = std::fs::read_link(&target).map_err(|e| format!("{}: {e}", path.display()))?;
                target = match target.parent() {
                    Some(dir) => dir.join(link),
                    None => link,
                };
            }
            Ok(m) if m.is_file() => return Ok(target),
            Ok(_) => return Err(format!("{}: not a regular file (a directory, pipe or device)", path.display())),
            Err(_) => {
                let dir = target.parent().filter(|d| !d.as_os_str().is_empty()).unwrap_or(Path::new("."));
                return if dir.is_dir() {
                    Ok(target)
                } else {
                    Err(format!("{}: directory {} does not exist", path.display(), dir.display()))
                };
            }
        }
    }
    Err(format!("{}: too many levels of symbolic links", path.display()))
}

pub fn save_png(path: &Path, width: u32, height: u32, rgba: &[u8]) -> anyhow::Result<()> {
    // Checked here: the encoder panics on a buffer of another size, leaving its file.
    if rgba.len() as u64 != 4 * u64::from(width) * u64::from(height) {
        anyhow::bail!("{}: no {width} x {height} picture to write ({} bytes drawn)", path.display(), rgba.len());
    }
    write_atomic(path, |tmp| {
        image::save_buffer_with_format(
            tmp,
            rgba,
            width,
            height,
            image::ExtendedColorType::Rgba8,
            image::ImageFormat::Png,
        )
        .map_err(|e| anyhow::anyhow!("{}: cannot write PNG: {e}", path.display()))
    })
}

/// Registers DejaVu Sans for plotters once; false (and a warning) when it is missing.
pub fn plot_font() -> bool {
    use plotters::prelude::FontStyle;
    static FONT: std::sync::OnceLock<bool> = std::sync::OnceLock::new();
    let have_font = *FONT.get_or_init(|| {
        ["/usr/share/fonts/truetype/dejavu/DejaVuSans.ttf", "/usr/share/fonts/TTF/DejaVuSans.ttf"]
            .iter()
            .find_map(|p| std::fs::read(p).ok())
            .map(|bytes| {
                plotters::style::register_font("sans-serif", FontStyle::Normal, Box::leak(bytes.into_boxed_slice()))
                    .is_ok()
            })
            .unwrap_or(false)
    });
    if !have_font {
        tracing::warn!("no DejaVuSans.ttf (Debian: fonts-dejavu-core): plots have no labels");
    }
    have_font
}

/// What every JSON output says about the terrain: where it is and its scale (SPEC
/// section 9) as the loader decided them, and the voids it filled.
#[derive(Clone, Debug, Default, serde::Serialize)]
pub struct TerrainFacts {
    /// The CRS ("EPSG:4326"), or null when the file has none.
    pub crs: Option<String>,
    /// World metres per sample along x (columns) and z (rows).
    pub spacing_m: [f32; 2],
    /// Metres per raw height unit.
    pub height_scale_m: f32,
    /// CRS coordinates of the first sample's centre (null without a CRS or world file).
    pub origin: Option<[f64; 2]>,
    /// Samples in the true extent (columns, rows).
    pub samples: [usize; 2],
    /// Void (nodata) samples filled at load.
    pub void_samples: usize,
    /// Whether they are drawn ("fill") or cut out ("hole").
    pub voids: crate::input::load::VoidMode,
    /// Whether heights are metres above sea level ("absolute": water at or below 0 m) or
    /// only relative (the lowest ground is water).
    pub heights: crate::input::georef::Heights,
}

impl TerrainFacts {
    /// The facts of a terrain in this frame, its voids filled and drawn.
    pub fn of_frame(
        g: &crate::lod::heightfield::Georef,
        spacing_m: [f32; 2],
        height_scale_m: f32,
        samples: [usize; 2],
        void_samples: usize,
    ) -> Self {
        TerrainFacts {
            crs: g.crs.clone(),
            spacing_m,
            height_scale_m,
            origin: (g.step != [0.0; 2]).then_some(g.origin),
            samples,
            void_samples,
            voids: crate::input::load::VoidMode::Fill,
            heights: crate::input::georef::Heights::of(g.absolute_heights),
        }
    }

    pub fn of(hf: &crate::lod::heightfield::Heightfield) -> Self {
        let facts = Self::of_frame(
            &hf.georef,
            [hf.spacing.x, hf.spacing.z],
            hf.height_scale,
            [hf.width, hf.height],
            hf.void_samples,
        );
        match hf.void_mask {
            Some(_) => TerrainFacts { voids: crate::input::load::VoidMode::Hole, ..facts },
            None => facts,
        }
    }

    /// The facts an archive's metadata records (voids were filled by `prepare`, and are
    /// drawn as holes where the archive, as opened, keeps their mask).
    pub fn of_meta(m: &crate::input::archive::Meta) -> Self {
        let facts = Self::of_frame(&m.georef, m.spacing, m.height_scale, [m.width, m.height], m.void_samples);
        let voids = if m.void_mask { crate::input::load::VoidMode::Hole } else { facts.voids };
        TerrainFacts { voids, ..facts }
    }

    /// [`TerrainFacts::of_meta`] with `--spacing` and `--height-scale` where `frame`
    /// gives them (the streamed terrain is drawn at those).
    pub fn of_archive(m: &crate::input::archive::Meta, frame: &crate::app::cli::FrameArgs) -> Self {
        TerrainFacts {
            spacing_m: frame.spacing.map_or(m.spacing, |s| [s.x, s.z]),
            height_scale_m: frame.height_scale.unwrap_or(m.height_scale),
            ..Self::of_meta(m)
        }
    }

    /// Adds these fields to a JSON object.
    pub fn merge_into(&self, out: &mut serde_json::Value) {
        if let (Some(o), serde_json::Value::Object(me)) =
            (out.as_object_mut(), serde_json::to_value(self).unwrap_or_default())
        {
            o.extend(me);
        }
    }
}

/// Whether `path` names a PNG file by its extension (any case).
pub fn is_png(path: &Path) -> bool {
    path.extension().and_then(|e| e.to_str()).is_some_and(|e| e.eq_ignore_ascii_case("png"))
}

/// This process's peak resident memory (VmHWM) in MB, where /proc says it (Linux).
pub fn peak_resident_mb() -> Option<f64> {
    let status = std::fs::read_to_string("/proc/self/status").ok()?;
    let line = status.lines().find(|l| l.starts_with("VmHWM:"))?;
    let kb: f64 = line.split_whitespace().nth(1)?.parse().ok()?;
    Some(kb / 1024.0)
}

/// The next `vkterrain-N.png` in the working directory that does not exist (the viewers'
/// P key).
pub fn next_free_screenshot() -> std::path::PathBuf {
    (1..)
        .map(|n| std::path::PathBuf::from(format!("vkterrain-{n}.png")))
        .find(|p| std::fs::symlink_metadata(p).is_err())
        .expect("a free name")
}

/// `println!` for the front-ends' output: `crate::out!(...)?` ends the run with an error
/// where standard output cannot be written (see [`write_stdout`]).
#[macro_export]
macro_rules! out {
    ($($arg:tt)*) => {
        $crate::app::outputs::write_stdout(format_args!($($arg)*))
    };
}

/// Writes one line to standard output: an error where it cannot be written (a closed pipe,
/// a full disk), which ends the run with exit code 1 and one line, not a panic as
/// `println!` would. Used through [`crate::out!`].
pub fn write_stdout(args: std::fmt::Arguments) -> anyhow::Result<()> {
    use std::io::Write;
    let mut o = std::io::stdout().lock();
    o.write_fmt(args)
        .and_then(|_| o.write_all(b"\n"))
        .and_then(|_| o.flush())
        .map_err(|e| anyhow::anyhow!("writing to standard output: {e}"))
}

/// The value at fraction `p` (0 to 1) of `sorted` (ascending), nearest rank; 0 when empty.
pub fn percentile(sorted: &[f64], p: f64) -> f64 {
    if sorted.is_empty() {
        return 0.0;
    }
    sorted[((sorted.len() - 1) as f64 * p).round() as usize]
}

/// The median of `v` (any order), `None` when empty.
pub fn median(v: &[f64]) -> Option<f64> {
    let mut s = v.to_vec();
    s.sort_by(f64::total_cmp);
    (!s.is_empty()).then(|| percentile(&s, 0.5))
}

/// What a viewer run did, printed as one JSON line at exit: the same fields whatever the
/// terrain is drawn from (null where a figure does not apply: no tiles read in memory).
#[derive(Default, serde::Serialize)]
pub struct ViewerReport {
    /// Drawn from tiles (a terrain larger than one image, `--stream`, a budget given).
    pub streamed: bool,
    pub frames: u64,
    pub seconds: f64,
    pub avg_fps: f64,
    /// Swapchains made again after the window's size changed.
    pub resizes: u64,
    /// Error generations handed to the draw thread, and the most in flight at once
    /// (`--error-pacing`).
    pub error_generations: u64,
    pub most_generations_in_flight: u64,
    /// Frames drawn with a block over the bound (its tile not held yet; never in memory),
    /// and the worst factor over it.
    pub frames_over_bound: u64,
    pub worst_factor: f32,
    /// The last frame's triangles, draw calls and blocks.
    pub last_triangles: u64,
    pub last_draw_calls: u64,
    pub last_blocks: usize,
    /// Bytes of the one block mesh every block is drawn from.
    pub geometry_bytes: u64,
    pub device: String,
    pub queue_mode: String,
    /// Validation messages (null when validation was off).
    pub validation_messages: Option<u64>,
    #[serde(flatten)]
    pub camera: ViewerCamera,
    #[serde(flatten)]
    pub state: ViewerState,
    pub screenshot: Option<String>,
    /// Frames drawn with the panel.
    pub hud_frames: u64,
    /// The tiles read and held, and the GPU side of frames drawn from tiles.
    pub stream: Option<crate::stream::streamer::StreamStats>,
    pub gpu: Option<serde_json::Value>,
    /// The first tile that could not be read: frames were drawn coarser than their data
    /// (`degraded`, exit code 3).
    pub first_failure: Option<String>,
    pub degraded: bool,
    /// Ended by a signal (Ctrl-C, SIGTERM), not by the window or --frames.
    pub interrupted: bool,
    /// Where the terrain is and its scale.
    #[serde(flatten)]
    pub terrain: TerrainFacts,
}

/// Where the viewer's camera went ([`ViewerReport`]).
#[derive(Default, serde::Serialize)]
pub struct ViewerCamera {
    /// The camera's latitude and longitude at exit, and the ground point under the
    /// cursor (latitude, longitude, ground height in metres, world position), when the
    /// terrain is georeferenced.
    pub camera_lat_lon: Option<[f64; 2]>,
    pub cursor_place: Option<serde_json::Value>,
    /// Position, yaw and pitch (radians) at exit, and where the camera started.
    pub final_position: [f32; 3],
    pub final_yaw: f32,
    pub final_pitch: f32,
    pub start_position: [f32; 3],
    /// Yaw turned by dragging the mouse; of it, in orbit mode; the largest change of the
    /// distance to the orbit's centre while orbiting (relative); how far pressing O
    /// turned the camera to face the point under the cursor.
    pub mouse_turn: f32,
    pub orbit_turn: f32,
    pub orbit_drift: f32,
    pub orbit_aim_turn: f32,
    /// Whether the camera orbited a ground point at exit (O).
    pub orbiting: bool,
}

/// What the keys and the panel left set at exit ([`ViewerReport`]).
#[derive(Default, serde::Serialize)]
pub struct ViewerState {
    pub final_delta: f32,
    /// Geomorphing (N) and the error mode (M).
    pub final_morph: bool,
    pub final_error_mode: &'static str,
    /// A frozen selection drawn (Space), edges only (F).
    pub frozen: bool,
    pub wireframe: bool,
    /// Vertical exaggeration.
    pub exaggeration: f32,
    /// The sun the frames were lit by (azimuth, elevation), if any.
    pub final_sun: Option<[f32; 2]>,
    /// Whether the panel was shown.
    pub hud_visible: bool,
}
