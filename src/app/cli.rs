//! Command-line options shared by the drawing subcommands (`view`, `render`, `errors`,
//! `bench`, `quality`: same names, same meanings).

use crate::draw::blocks::Shading;
use crate::gpu::terrain::Texture;
use crate::input::load::{self, LoadOptions, VoidMode};
use crate::lod::camera::Camera;
use crate::lod::gie::ErrorMode;
use crate::lod::heightfield::{Heightfield, Spacing};
use crate::lod::view::{default_view, near_plane};
use crate::vk::QueueRequest;
use clap::{Args, ValueEnum};
use glam::Vec3;
use std::path::PathBuf;

/// An error in the user's input (exit code 2), as opposed to a runtime failure.
#[derive(Debug, thiserror::Error)]
#[error("{0}")]
pub struct InputError(pub String);

/// The archive a command reads: positional, or `--heightmap` as the drawing commands
/// name their terrain.
#[derive(Args, Clone, Debug)]
pub struct ArchiveInput {
    /// The archive (written by `vkterrain prepare`): a path or an http(s):// URL.
    #[arg(value_name = "ARCHIVE", required_unless_present = "heightmap", conflicts_with = "heightmap")]
    archive: Option<PathBuf>,
    /// The same as ARCHIVE, as an option.
    #[arg(long, value_name = "FILE")]
    heightmap: Option<PathBuf>,
}

impl ArchiveInput {
    pub fn path(&self) -> &std::path::Path {
        // clap requires one of the two.
        self.archive.as_deref().or(self.heightmap.as_deref()).unwrap_or(std::path::Path::new(""))
    }
}

/// A run that finished and wrote what it was asked for, but degraded: tiles that could
/// not be read, frames drawn without their data (exit code 3). Its JSON says
/// `"degraded": true`.
#[derive(Debug, thiserror::Error)]
#[error("finished degraded: {0}")]
pub struct Degraded(pub String);

/// A run stopped by a signal after writing its partial outputs (exit code 128 + the
/// signal, as a shell reports a process the signal ended). Its JSON, where it writes
/// one, says `"interrupted": true`.
#[derive(Debug, thiserror::Error)]
#[error("interrupted: {what}")]
pub struct Interrupted {
    /// 128 + the signal.
    pub code: u8,
    /// What was written before stopping.
    pub what: String,
}

impl Interrupted {
    pub fn by(stop: &crate::app::signals::Stop, what: impl Into<String>) -> Interrupted {
        Interrupted { code: stop.exit_code().clamp(129, 255) as u8, what: what.into() }
    }
}

/// The exit code for a run's error: 2 bad input, 3 finished degraded, 128 + a signal when
/// interrupted, 1 anything else (an internal or device error).
pub fn exit_code(e: &anyhow::Error) -> u8 {
    if e.downcast_ref::<InputError>().is_some() {
        2
    } else if e.downcast_ref::<Degraded>().is_some() {
        3
    } else if let Some(i) = e.downcast_ref::<Interrupted>() {
        i.code
    } else {
        1
    }
}

#[derive(Clone, Copy, Debug, PartialEq, Eq, ValueEnum)]
pub enum OnOff {
    On,
    Off,
}

/// `--validation on|off`, the same for every command: on in debug builds unless given.
pub fn validation_on(v: Option<OnOff>) -> bool {
    match v {
        Some(OnOff::On) => true,
        Some(OnOff::Off) => false,
        None => cfg!(debug_assertions),
    }
}

/// The command-line spelling of a value-enum option (`deferred`, `gradient-map`).
pub fn value_name(v: impl clap::ValueEnum) -> String {
    v.to_possible_value().map(|p| p.get_name().to_string()).unwrap_or_default()
}

pub fn parse_size(s: &str) -> Result<(u32, u32), String> {
    let (w, h) = s.split_once(['x', 'X']).ok_or_else(|| format!("'{s}': expected WIDTHxHEIGHT, e.g. 1280x720"))?;
    let side = |v: &str, what: &str| -> Result<u32, String> {
        let v = v.trim();
        match v.parse::<u32>() {
            Ok(n) => Ok(n),
            // All digits, yet no u32: too large for any image, not malformed.
            Err(_) if !v.is_empty() && v.bytes().all(|b| b.is_ascii_digit()) => {
                Err(format!("'{s}': {what} {v} is larger than any image"))
            }
            Err(_) => Err(format!("'{s}': {what} is not a whole number")),
        }
    };
    let (w, h) = (side(w, "width")?, side(h, "height")?);
    if w == 0 || h == 0 {
        return Err(format!("'{s}': width and height must be at least 1"));
    }
    Ok((w, h))
}

fn parse_vec3(s: &str) -> Result<Vec3, String> {
    let parts: Vec<&str> = s.split(',').collect();
    if parts.len() != 3 {
        return Err(format!("'{s}': expected X,Y,Z"));
    }
    let mut v = [0.0f32; 3];
    for (i, p) in parts.iter().enumerate() {
        v[i] = p.trim().parse().map_err(|_| format!("'{s}': '{p}' is not a number"))?;
        if !v[i].is_finite() {
            return Err(format!("'{s}': coordinates must be finite numbers"));
        }
    }
    Ok(Vec3::from_array(v))
}

/// Parses a finite number greater than 0.
pub fn positive(s: &str) -> Result<f32, String> {
    let v: f32 = s.parse().map_err(|_| format!("'{s}' is not a number"))?;
    if !(v.is_finite() && v > 0.0) {
        return Err(format!("'{s}': must be a finite number greater than 0"));
    }
    Ok(v)
}

pub fn non_negative(s: &str) -> Result<f32, String> {
    let v: f32 = s.parse().map_err(|_| format!("'{s}' is not a number"))?;
    if !(v.is_finite() && v >= 0.0) {
        return Err(format!("'{s}': must be a finite number, 0 or more"));
    }
    Ok(v)
}

pub fn at_least_one(s: &str) -> Result<u64, String> {
    match s.parse::<u64>() {
        Ok(n) if n >= 1 => Ok(n),
        _ => Err(format!("'{s}': must be a whole number, 1 or more")),
    }
}

fn parse_fraction(s: &str) -> Result<f32, String> {
    let v: f32 = s.parse().map_err(|_| format!("'{s}' is not a number"))?;
    if !(0.0..1.0).contains(&v) {
        return Err(format!("'{s}': must be at least 0 and below 1"));
    }
    Ok(v)
}

fn parse_share(s: &str) -> Result<f32, String> {
    let v: f64 = s.parse().map_err(|_| format!("'{s}' is not a number"))?;
    if !(v > 0.0 && v <= 1.0) {
        return Err(format!("'{s}': must be above 0 and at most 1"));
    }
    if (v as f32) < f32::MIN_POSITIVE {
        return Err(format!("'{s}': too small (at least {:e})", f32::MIN_POSITIVE));
    }
    Ok(v as f32)
}

fn parse_fovy(s: &str) -> Result<f32, String> {
    let v = positive(s)?;
    if v >= 179.0 {
        return Err(format!("'{s}': the field of view must be below 179 degrees"));
    }
    Ok(v)
}

pub fn parse_spacing(s: &str) -> Result<Spacing, String> {
    match s.split_once(',') {
        Some((x, z)) => Ok(Spacing { x: positive(x.trim())?, z: positive(z.trim())? }),
        None => positive(s).map(Spacing::from),
    }
}

/// What the user declares about a terrain's frame, over what the file (or archive) says:
/// the same three flags wherever a terrain is opened or prepared.
#[derive(Args, Clone, Copy, Debug, Default)]
pub struct FrameArgs {
    /// Metres between samples, or X,Z for different spacings along columns (x) and rows
    /// (z). Default: what the file's georeferencing says (printed at load).
    #[arg(long, value_name = "M[,Z]", value_parser = parse_spacing, allow_negative_numbers = true)]
    pub spacing: Option<Spacing>,
    /// Metres per height unit. Default: what the file says (printed at load).
    #[arg(long, value_name = "M", value_parser = positive, allow_negative_numbers = true)]
    pub height_scale: Option<f32>,
    /// Whether heights are metres above sea level (absolute: water at or below 0 m,
    /// colours by height in metres) or only relative (the lowest ground is water, colours
    /// span the range). Default: absolute when the file names its CRS, else relative.
    #[arg(long, value_enum, value_name = "absolute|relative")]
    pub heights: Option<crate::input::georef::Heights>,
}

impl FrameArgs {
    pub fn declared(&self) -> crate::input::georef::Declared {
        crate::input::georef::Declared { spacing: self.spacing, height_scale: self.height_scale, heights: self.heights }
    }
}

/// The terrain a command draws or flies over, and how to read it: the same options
/// wherever a terrain is opened.
#[derive(Args, Clone, Debug)]
pub struct TerrainArgs {
    /// The terrain: a heightfield file (GeoTIFF, .hgt, PNG, JPEG, .r16, .f32, anything
    /// GDAL reads), an archive written by `vkterrain prepare`, or an archive's http(s)://
    /// URL. Default: the built-in procedural terrain (2049 x 2049, 30 m spacing).
    #[arg(value_name = "TERRAIN", conflicts_with = "heightmap")]
    pub file: Option<PathBuf>,
    /// The same as TERRAIN, as an option.
    #[arg(long, value_name = "FILE")]
    pub heightmap: Option<PathBuf>,
    /// Size of a raw .r16/.f32 heightfield.
    #[arg(long, value_name = "WxH", value_parser = parse_size, allow_hyphen_values = true)]
    pub raw_size: Option<(u32, u32)>,
    /// What the user declares about the terrain's frame.
    #[command(flatten)]
    pub frame: FrameArgs,
    /// What voids (nodata samples) become: filled smoothly and drawn, or holes in the
    /// picture (still filled for the LOD bound; shading is then forward).
    #[arg(long, value_enum, default_value_t = VoidMode::Fill)]
    pub voids: VoidMode,
}

/// What the camera sees: the viewport and the field of view.
#[derive(Args, Clone, Copy, Debug)]
pub struct FrustumArgs {
    /// Viewport size in pixels.
    #[arg(long, value_name = "WxH", value_parser = parse_size, allow_hyphen_values = true)]
    pub size: Option<(u32, u32)>,
    /// Vertical field of view in degrees.
    #[arg(long, value_name = "DEG", default_value = "60", value_parser = parse_fovy, allow_negative_numbers = true)]
    pub fovy: f32,
}

/// Where the camera stands and what it looks at.
#[derive(Args, Clone, Copy, Debug)]
pub struct CameraArgs {
    #[command(flatten)]
    pub frustum: FrustumArgs,
    /// Camera position in world units (x east, y up, z south). Default: above one edge,
    /// seeing the whole terrain.
    #[arg(long = "camera", value_name = "X,Y,Z", value_parser = parse_vec3, allow_hyphen_values = true)]
    pub position: Option<Vec3>,
    /// Point the camera looks at. Default: the terrain's centre.
    #[arg(long, value_name = "X,Y,Z", value_parser = parse_vec3, allow_hyphen_values = true)]
    pub look_at: Option<Vec3>,
}

/// The Vulkan device a command runs on, and how it is checked.
#[derive(Args, Clone, Debug)]
pub struct DeviceArgs {
    /// Vulkan validation (with synchronization validation). Default: on in debug builds.
    #[arg(long, value_enum)]
    pub validation: Option<OnOff>,
    /// GPU to use, by index or name substring (default: prefer a discrete GPU).
    #[arg(long, value_name = "NAME|INDEX")]
    pub gpu: Option<String>,
    /// Queue arrangement for the two activities.
    #[arg(long, value_enum, default_value_t = QueueRequest::Auto)]
    pub queues: QueueRequest,
}

impl DeviceArgs {
    pub fn validation(&self) -> bool {
        validation_on(self.validation)
    }
}

/// `--block`: the side of the blocks every LOD is drawn with.
#[derive(Args, Clone, Copy, Debug)]
pub struct BlockArg {
    /// Block side k = 2^m + 1 vertices: every block is drawn from one k x k mesh, so a
    /// larger k draws fewer, larger blocks (fewer draw calls, more triangles for the
    /// same delta). A terrain drawn from tiles takes 9 to 129.
    #[arg(long = "block", value_name = "K", default_value_t = crate::lod::block::DEFAULT_K, allow_negative_numbers = true)]
    pub k: u32,
}

/// `--error-mode`: which screen-space error bounds the blocks.
#[derive(Args, Clone, Copy, Debug)]
pub struct ErrorModeArg {
    /// Screen-space error bound: strict (guaranteed for every camera) or paper (the
    /// published method's per-vertex estimate, from the heights of each group).
    #[arg(long = "error-mode", alias = "mode", value_enum, default_value_t = ErrorMode::Strict)]
    pub mode: ErrorMode,
}

/// `--morph`: geomorphing.
#[derive(Args, Clone, Copy, Debug)]
pub struct MorphArg {
    /// Geomorphing: blocks move continuously between LODs instead of popping, with the
    /// morph paid for inside the error bound.
    #[arg(long = "morph", value_name = "MORPH", value_enum, default_value_t = OnOff::On)]
    pub setting: OnOff,
}

impl MorphArg {
    pub fn on(&self) -> bool {
        self.setting == OnOff::On
    }
}

/// How a frame's blocks are chosen: the threshold, the morph, the traversal's threads.
#[derive(Args, Clone, Copy, Debug)]
pub struct LodArgs {
    /// Screen-space error threshold delta, in pixels: a block is split while its error
    /// exceeds it. Smaller draws more triangles and a surface closer to every sample.
    #[arg(long, value_name = "PX", default_value = "1", value_parser = positive, allow_negative_numbers = true)]
    pub delta: f32,
    #[command(flatten)]
    pub morph: MorphArg,
    /// Threads for the traversal's per-block work (the morph's bounds). Default: 1 on a
    /// CPU device such as lavapipe, where a pool's workers beside the rasterizer's threads
    /// made the traversal slower; every core on a GPU, where the frame waits for the
    /// traversal.
    #[arg(long, value_name = "N", value_parser = clap::value_parser!(u16).range(1..=256), allow_negative_numbers = true)]
    pub traversal_threads: Option<u16>,
}

/// Options the drawing subcommands share.
#[derive(Args, Clone, Debug)]
pub struct CommonArgs {
    #[command(flatten)]
    pub terrain: TerrainArgs,
    #[command(flatten)]
    pub view: CameraArgs,
    #[command(flatten)]
    pub block: BlockArg,
    #[command(flatten)]
    pub device: DeviceArgs,
    /// New error data is requested when the camera has moved this fraction of the
    /// distance to the nearest drawn terrain since the last request and the last frame
    /// split blocks only because its data was stale (0: every frame it moves, stale
    /// splits or not). Stale data keeps the bound; this only trades updates for triangles.
    #[arg(long, value_name = "F", default_value = "0.05", value_parser = parse_fraction, allow_negative_numbers = true)]
    pub refresh_at: f32,
    /// Largest share of wall time spent on error updates (1: no cap). After an update of
    /// u ms the next request waits u (1/share - 1) ms; stale data keeps the bound.
    #[arg(long, value_name = "SHARE", default_value = "0.05", value_parser = parse_share, allow_negative_numbers = true)]
    pub update_share: f32,
    /// How the errors thread submits a generation's parts: auto (paced on a shared queue,
    /// free with separate queues), paced (each part waits for the one before, so draws
    /// run in between and the GPU has one generation at a time), or free (at once: a
    /// second generation may queue behind the first, both slots written).
    #[arg(long, value_enum, default_value_t = crate::errors::activity::Pacing::Auto)]
    pub error_pacing: crate::errors::activity::Pacing,
    #[command(flatten)]
    pub error_mode: ErrorModeArg,
    #[command(flatten)]
    pub lod: LodArgs,
    /// Occlusion culling: blocks, and 4 x 4 parts of blocks, hidden behind nearer terrain
    /// are not drawn (provably conservative; skipped, with the reason in the stats, where
    /// the proof does not hold). Default: on.
    #[arg(long, value_enum)]
    pub occlusion: Option<OnOff>,
    /// Sun for the precomputed shadows and ambient occlusion: compass azimuth and
    /// elevation in degrees (azimuth 0 is north, the top of the heightmap), or `off`.
    #[arg(long, value_name = "AZ,EL|off", default_value = "301,54", value_parser = parse_sun, allow_negative_numbers = true)]
    pub sun: SunArg,
}

impl TerrainArgs {
    /// The terrain given as TERRAIN becomes `heightmap`, the one field the commands read.
    pub fn take_terrain(&mut self) {
        if let Some(t) = self.file.take() {
            self.heightmap = Some(t);
        }
    }

    /// The terrain file, checked before anything else opens (a device, a window): one
    /// line naming it when it is missing or not a regular file (a URL is checked when read).
    pub fn check_terrain(&self) -> Result<(), InputError> {
        match self.heightmap.as_deref() {
            Some(path) if !crate::input::archive::bytes::is_url(path) => {
                crate::input::regular_file(path).map(|_| ()).map_err(InputError)
            }
            _ => Ok(()),
        }
    }

    /// Loads `--heightmap` (or the built-in terrain); `max_grid_side` is the device's
    /// image size limit when the device already exists.
    pub fn load_heightfield(&self, max_grid_side: Option<usize>) -> Result<Heightfield, InputError> {
        match &self.heightmap {
            None => Ok(crate::input::procedural::procedural()),
            Some(path) => {
                let opts = LoadOptions {
                    spacing: self.frame.spacing,
                    height_scale: self.frame.height_scale,
                    heights: self.frame.heights,
                    raw_size: self.raw_size.map(|(w, h)| (w as usize, h as usize)),
                    max_grid_side,
                    voids: self.voids,
                    no_holes: false,
                };
                let hf = load::load(path, &opts).map_err(|e| InputError(e.to_string()))?;
                for line in crate::input::describe(&hf) {
                    eprintln!("vkterrain: note: {line}");
                }
                check_scale(&hf)?;
                Ok(hf)
            }
        }
    }

    /// How the terrain is named to the user: the file or URL given, or the built-in one.
    pub fn name(&self) -> String {
        self.heightmap.as_deref().map_or_else(|| "the built-in terrain".into(), crate::input::archive::bytes::shown)
    }
}

/// The `--sun` option: a sun, or none (no shadows or occlusion).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SunArg(pub Option<crate::draw::lighting::Sun>);

fn parse_sun(s: &str) -> Result<SunArg, String> {
    crate::draw::lighting::Sun::parse(s).map(SunArg)
}

impl CameraArgs {
    pub fn camera(&self, hf: &Heightfield, default_size: (u32, u32)) -> Result<Camera, InputError> {
        let (w, h) = self.frustum.size.unwrap_or(default_size);
        let (position, look_at) = self.view_points(|| default_view(hf, self.frustum.fovy, w, h))?;
        Ok(Camera::look_at(position, look_at, self.frustum.fovy, w, h, near_plane(hf)))
    }

    /// `--camera` and `--look-at`, each from `default` (camera, target) when not given,
    /// checked: distinct, and within [`MAX_WORLD`].
    pub fn view_points(&self, default: impl FnOnce() -> (Vec3, Vec3)) -> Result<(Vec3, Vec3), InputError> {
        let (pos, target) = match (self.position, self.look_at) {
            (Some(c), Some(l)) => (c, l),
            _ => default(),
        };
        let position = self.position.unwrap_or(pos);
        let look_at = self.look_at.unwrap_or(target);
        if (look_at - position).length() < 1e-6 {
            return Err(InputError("--look-at must differ from --camera".into()));
        }
        if !(position.abs().max_element() <= MAX_WORLD && look_at.abs().max_element() <= MAX_WORLD) {
            return Err(InputError(format!(
                "the camera ({position}) or the point it looks at ({look_at}) is beyond {MAX_WORLD:e} world units \
                 (single-precision positions)"
            )));
        }
        Ok((position, look_at))
    }
}

/// The host cache budget, MB, of a terrain when none is given, at least.
pub const DEFAULT_CACHE_MB: u32 = 256;

/// How an archive is drawn streamed (`render`, `view`): forced, and the budgets.
#[derive(Args, Debug, Clone, Copy)]
pub struct StreamedOptions {
    /// Draw the terrain from its tiles (through a host cache and a GPU atlas, in bounded
    /// memory) even when it fits in one image: a file, or the built-in terrain, is cut
    /// into tiles in memory first. Terrains larger than one image are always drawn so.
    #[arg(long)]
    pub stream: bool,
    /// Host cache budget for decoded tiles, MB [default: 256, or every tile of a terrain
    /// the default atlas holds whole]; given, the terrain is drawn from its tiles (as with
    /// --stream).
    #[arg(long = "cache-mb", value_name = "MB", value_parser = clap::value_parser!(u32).range(1..=1_000_000), allow_negative_numbers = true)]
    pub cache_mb_given: Option<u32>,
    /// GPU atlas budget, MB (one layer a tile, at most 2048 layers) [default: every tile
    /// of the terrain when they fit, else 256]; given, the terrain is drawn from its tiles
    /// (as with --stream).
    #[arg(long = "gpu-mb", value_name = "MB", value_parser = clap::value_parser!(u32).range(1..=1_000_000), allow_negative_numbers = true)]
    pub gpu_mb_given: Option<u32>,
}

impl StreamedOptions {
    /// The host cache budget for the terrain of `m`: as given, or by default 256 MB, and
    /// when the default atlas holds every tile ([`Self::gpu_mb`]) enough for every tile
    /// too, so that such a terrain is wholly resident. The cache charges each tile at
    /// least its share of the budget (one share a layer: `HostCache::limit_tiles`), so
    /// that is the tiles times the largest a tile takes: a tile of a coarser level with
    /// its `D`, or the top one with every coarser LOD's.
    pub fn cache_mb(&self, m: &crate::input::archive::Meta) -> u32 {
        self.cache_mb_given.unwrap_or_else(|| {
            let grid = crate::stream::Grid::from_meta(m);
            let tiles: usize =
                (0..=grid.top).map(|l| grid.tiles_at(l).iter().map(|&n| n as usize).product::<usize>()).sum();
            let whole = self.gpu_mb_given.is_none() && tiles <= crate::errors::atlas::MAX_LAYERS as usize;
            let t = grid.tile_quads;
            let largest = crate::stream::cache::tile_bytes_estimate(&grid, grid.top.max(1)) + (t * t * 4).div_ceil(3);
            let mb = if whole { (tiles * largest).div_ceil(1 << 20) as u32 } else { 0 };
            mb.max(DEFAULT_CACHE_MB)
        })
    }
    /// The atlas budget for the terrain of `m`: as given, or by default every tile when
    /// they fit the atlas's layers ([`crate::errors::atlas::HeightAtlas::default_budget_mb`]).
    pub fn gpu_mb(&self, m: &crate::input::archive::Meta) -> u32 {
        let grid = crate::stream::Grid::from_meta(m);
        self.gpu_mb_given.unwrap_or_else(|| crate::errors::atlas::HeightAtlas::default_budget_mb(&grid))
    }
    /// Whether the terrain is to be drawn from its tiles whatever its size: `--stream`,
    /// or a budget for them given (it would mean nothing otherwise).
    pub fn from_tiles(&self) -> bool {
        self.stream || self.cache_mb_given.is_some() || self.gpu_mb_given.is_some()
    }
}

/// An error if the validation layers said anything: a run under validation fails on any
/// message.
pub fn check_messages(messages: &crate::vk::MessageCounter) -> anyhow::Result<()> {
    let n = messages.count();
    if n > 0 {
        anyhow::bail!("{n} validation message(s); first: {}", messages.messages().first().cloned().unwrap_or_default());
    }
    Ok(())
}

/// An image size option (`--size`, a window's) must fit in one image on `device` (exit
/// code 2 naming the option, not a failure when the image is made).
pub fn check_image_size(device: &crate::vk::Device, option: &str, (w, h): (u32, u32)) -> Result<(), InputError> {
    let max = device.max_image_dimension_2d();
    if w > max || h > max {
        return Err(InputError(format!("{option} {w}x{h}: larger than the device's maxImageDimension2D ({max})")));
    }
    Ok(())
}

/// A device that cannot satisfy `--gpu` or `--queues` is a bad option (exit code 2).
pub fn option_error(e: crate::vk::VkError) -> anyhow::Error {
    match e {
        crate::vk::VkError::Option(m) => InputError(m).into(),
        e => e.into(),
    }
}

pub use crate::lod::heightfield::MAX_WORLD;

/// The terrain's world extent and heights must fit [`MAX_WORLD`].
pub fn check_scale(hf: &Heightfield) -> Result<(), InputError> {
    let (wx, wz) = hf.world_extent();
    let top = hf.raw.iter().fold(0.0f32, |m, v| m.max((v * hf.height_scale).abs()));
    if !(wx.max(wz) <= MAX_WORLD && top <= MAX_WORLD) {
        return Err(InputError(format!(
            "{}: {wx:e} x {wz:e} world units with heights up to {top:e}: beyond {MAX_WORLD:e} \
             (check --spacing and --height-scale)",
            hf.source
        )));
    }
    Ok(())
}

/// Texturing (Yusuf et al., eqs. 9-11), for every command that draws: `view`, `render`, `bench`.
#[derive(Args, Debug, Clone)]
pub struct TextureArgs {
    /// Base colour texture, stretched over the whole terrain.
    #[arg(long, value_name = "FILE")]
    pub texture: Option<PathBuf>,
    /// Detail texture, repeated over the terrain DTF times across the base texture.
    #[arg(long, value_name = "FILE")]
    pub detail: Option<PathBuf>,
    /// Detail tiling factor DTF: detail coordinates are DTF times the base coordinates.
    #[arg(long, value_name = "DTF", default_value = "64", value_parser = positive, allow_negative_numbers = true, requires = "detail")]
    pub detail_tiling: f32,
    /// Weight alpha of the base colour against the detail (1 ignores the detail texture).
    #[arg(long, value_name = "ALPHA", default_value = "0.7", allow_negative_numbers = true, requires = "detail")]
    pub detail_weight: f32,
}

/// The textures a [`TextureArgs`] names, read and checked.
#[derive(Default)]
pub struct Textures {
    pub base: Option<Texture>,
    pub detail: Option<Texture>,
}

impl TextureArgs {
    /// Each texture read for these options fits in one image on `device` (exit 2 naming
    /// the option and the file, not a failure when the image is made).
    pub fn check_fits(
        &self,
        base: Option<&Texture>,
        detail: Option<&Texture>,
        device: &crate::vk::Device,
    ) -> Result<(), InputError> {
        let max = device.max_image_dimension_2d();
        for (texture, option, path) in [(base, "--texture", &self.texture), (detail, "--detail", &self.detail)] {
            if let (Some(t), Some(path)) = (texture, path) {
                if t.width > max || t.height > max {
                    return Err(InputError(format!(
                        "{option} {}: {} x {} texels is larger than the device's maxImageDimension2D ({max})",
                        path.display(),
                        t.width,
                        t.height
                    )));
                }
            }
        }
        Ok(())
    }

    /// Input paths, for the commands' output checks.
    pub fn inputs(&self) -> [(&'static str, Option<&std::path::Path>); 2] {
        [("--texture", self.texture.as_deref()), ("--detail", self.detail.as_deref())]
    }

    /// Reads the textures (each error names the option and the file). A georeferenced
    /// base texture over a georeferenced terrain is warped onto it by both files'
    /// georeferencing ([`crate::input::georef::drape`]); any other is stretched over the
    /// terrain's extent.
    pub fn load(&self, hf: &Heightfield) -> Result<Textures, InputError> {
        self.load_over(&hf.georef, (hf.width, hf.height))
    }

    /// [`TextureArgs::load`] over a terrain of `size` samples placed by `georef` (an
    /// archive's, whose samples are not all in memory).
    pub fn load_over(
        &self,
        georef: &crate::lod::heightfield::Georef,
        size: (usize, usize),
    ) -> Result<Textures, InputError> {
        if !(0.0..=1.0).contains(&self.detail_weight) {
            return Err(InputError(format!("--detail-weight {}: must be within 0..1", self.detail_weight)));
        }
        let read = |option: &str, path: &PathBuf| -> Result<Texture, InputError> {
            crate::input::regular_file(path).map_err(|e| InputError(format!("{option} {e}")))?;
            let img = image::open(path)
                .map_err(|e| InputError(format!("{option} {}: cannot read texture: {e}", path.display())))?;
            let rgba = img.to_rgba8();
            Ok(Texture { width: rgba.width(), height: rgba.height(), rgba: rgba.into_raw() })
        };
        let base = |path: &PathBuf| -> Result<Texture, InputError> {
            crate::input::regular_file(path).map_err(|e| InputError(format!("--texture {e}")))?;
            match crate::input::georef::drape(path, georef, size).map_err(|e| InputError(format!("--texture {e}")))? {
                Some((width, height, rgba)) => {
                    eprintln!(
                        "vkterrain: note: --texture {}: georeferenced, warped onto the terrain ({width} x {height} texels)",
                        path.display()
                    );
                    Ok(Texture { width, height, rgba })
                }
                None => {
                    // Stretched: say so when one side has coordinates the other lacks.
                    let terrain_placed = georef.step != [0.0; 2];
                    eprintln!(
                        "vkterrain: note: --texture {}: stretched over the terrain's whole extent{}",
                        path.display(),
                        if terrain_placed {
                            " (the image has no georeferencing to drape by)"
                        } else {
                            " (the terrain has no georeferencing)"
                        }
                    );
                    read("--texture", path)
                }
            }
        };
        Ok(Textures {
            base: self.texture.as_ref().map(base).transpose()?,
            detail: self.detail.as_ref().map(|p| read("--detail", p)).transpose()?,
        })
    }

    /// `shading` with the detail blend these options ask for (none without a detail texture).
    pub fn shade(&self, shading: Shading) -> Shading {
        let detail_weight = if self.detail.is_some() { self.detail_weight } else { 1.0 };
        Shading { detail_tiling: self.detail_tiling, detail_weight, ..shading }
    }
}
