//! `vkterrain prepare`: the front-end of [`crate::prepare`] (inputs, progress bar,
//! Ctrl-C, the report).

use crate::app::cli::InputError;
use crate::app::signals::Stop;
use crate::input::georef::{self, WindowReader};
use crate::input::load::{self, LoadOptions, VoidMode};
use crate::lod::heightfield::Georef;
use crate::prepare::source::{FromArchive, InMemory, Synthetic, Windowed};
use crate::prepare::{Frame, PrepareError, Source};
use std::path::{Path, PathBuf};

#[derive(clap::Args, Debug)]
pub struct PrepareArgs {
    /// The terrain to prepare: any file the viewer opens (GeoTIFF, .hgt, PNG, raw, a GDAL
    /// .vrt, an archive or its URL); or many files or directories of tiles (SRTM .hgt,
    /// GeoTIFF tiles), mosaicked by their georeferencing. Not with --synthetic.
    #[arg(value_name = "INPUT", required_unless_present_any = ["synthetic", "heightmap"], conflicts_with = "synthetic", num_args = 1..)]
    pub input: Vec<PathBuf>,
    /// One more input, named as the drawing commands name their terrain.
    #[arg(long, value_name = "FILE", conflicts_with = "synthetic")]
    pub heightmap: Option<PathBuf>,
    /// The archive to write (PMTiles v3). It appears only when complete.
    #[arg(long, short)]
    pub out: PathBuf,
    /// Instead of a file: non-periodic fBm of SIDE x SIDE samples (30 m apart, 16-bit
    /// heights of 0.1 m), made window by window (any size).
    #[arg(long, value_name = "SIDE", value_parser = clap::value_parser!(u32).range(3..=1_048_577), allow_negative_numbers = true)]
    pub synthetic: Option<u32>,
    /// What the archive records of the terrain's frame, over what the input says.
    #[command(flatten)]
    pub frame: crate::app::cli::FrameArgs,
    /// Size of a raw .r16/.f32 input, as WIDTHxHEIGHT.
    #[arg(long, value_parser = crate::app::cli::parse_size, allow_hyphen_values = true)]
    pub raw_size: Option<(u32, u32)>,
    /// Read the input window by window even when it would fit in memory (inputs over
    /// 8193^2 samples always are). Voids are then refused, not filled.
    #[arg(long)]
    pub windows: bool,
    /// What the archive keeps of the input's voids (nodata samples): `fill` fills them
    /// smoothly, drawn as terrain; `hole` fills them too (for the LOD bound) and records
    /// which they were, so that `--voids hole` can cut them out of the picture. Needs
    /// the input read whole (not with --windows, nor over 8193^2 samples).
    #[arg(long, value_enum, default_value_t = VoidMode::Fill)]
    pub voids: VoidMode,
}

/// `--voids hole` over an archive (`shown` in messages) needs the mask of its voids, if
/// it had any: refused, saying how to keep them, where `prepare` filled them without one.
pub(crate) fn check_void_mask(
    shown: &str,
    meta: &crate::input::archive::Meta,
    voids: VoidMode,
) -> Result<(), InputError> {
    if voids == VoidMode::Hole && !meta.void_mask && meta.void_samples > 0 {
        return Err(InputError(format!(
            "{shown}: --voids hole: the archive's {} voids were filled when it was prepared, and where they were was not kept (prepare it from its source with --voids hole)",
            meta.void_samples
        )));
    }
    Ok(())
}

/// Inputs larger than this are read window by window (in memory they would take about
/// 8 bytes a sample, twice: the file's samples and the embedded grid).
pub const IN_MEMORY_SAMPLES: usize = 8193 * 8193;

/// Is `path` read window by window? Rasters GDAL reads, when asked to or when large;
/// raw files are read whole (archives are read tile by tile, before this is asked).
fn windowed(path: &std::path::Path, asked: bool) -> Result<bool, InputError> {
    let ext = path.extension().map(|e| e.to_string_lossy().to_lowercase()).unwrap_or_default();
    if matches!(ext.as_str(), "r16" | "f32" | "pmtiles") {
        if asked {
            return Err(InputError(format!(
                "{}: --windows reads GDAL rasters; raw files are read whole",
                path.display()
            )));
        }
        return Ok(false);
    }
    crate::input::regular_file(path).map_err(InputError)?;
    if asked {
        return Ok(true);
    }
    Ok(match WindowReader::open(path) {
        // Too many samples for memory, or a side longer than a whole read takes (a strip).
        Ok(r) => {
            r.raster.width * r.raster.height > IN_MEMORY_SAMPLES
                || r.raster.width.max(r.raster.height) > crate::lod::heightfield::MAX_SIDE
        }
        // The whole-file loader gives the full message.
        Err(_) => false,
    })
}

/// Refuses an `--out` that is the input itself (under any spelling: `./a/../a/x.tif`, a
/// link, a hard link): the archive would replace the terrain it is made from.
fn out_is_not_input(input: &std::path::Path, out: &std::path::Path) -> Result<(), InputError> {
    use std::os::unix::fs::MetadataExt;
    let (Ok(a), Ok(b)) = (std::fs::metadata(input), std::fs::metadata(out)) else {
        return Ok(()); // --out does not exist yet: it cannot be the input
    };
    if a.dev() == b.dev() && a.ino() == b.ino() {
        return Err(InputError(format!(
            "--out {}: is the input {} itself; name a new file for the archive",
            out.display(),
            input.display()
        )));
    }
    Ok(())
}

/// The files `inputs` name: files as given, directories as the elevation tiles in them
/// (sorted, so that a mosaic is the same every run).
fn expand_inputs(inputs: &[PathBuf]) -> Result<Vec<PathBuf>, InputError> {
    let mut files = Vec::new();
    for input in inputs {
        if !input.is_dir() {
            files.push(input.clone());
            continue;
        }
        let mut tiles = Vec::new();
        tiles_under(input, 0, &mut tiles)?;
        if tiles.is_empty() {
            return Err(InputError(format!(
                "{}: a directory with no elevation tiles in it or below it (.{})",
                input.display(),
                georef::TILE_EXTENSIONS.join(", .")
            )));
        }
        tiles.sort();
        files.extend(tiles);
    }
    Ok(files)
}

/// The elevation tiles in `dir` and its subdirectories (SRTM and Copernicus downloads
/// come as one folder per tile or per degree band). Symbolic links to directories are
/// not followed (a loop would never end); the depth is limited for the same reason.
fn tiles_under(dir: &Path, depth: usize, tiles: &mut Vec<PathBuf>) -> Result<(), InputError> {
    const MAX_DEPTH: usize = 8;
    let entries = std::fs::read_dir(dir).map_err(|e| InputError(format!("{}: {e}", dir.display())))?;
    for entry in entries.flatten() {
        let path = entry.path();
        let is_link = entry.file_type().is_ok_and(|t| t.is_symlink());
        if path.is_dir() {
            if !is_link && depth < MAX_DEPTH {
                tiles_under(&path, depth + 1, tiles)?;
            }
            continue;
        }
        let ext = path.extension().map(|e| e.to_string_lossy().to_lowercase()).unwrap_or_default();
        if path.is_file() && georef::TILE_EXTENSIONS.contains(&ext.as_str()) {
            tiles.push(path);
        }
    }
    Ok(())
}

/// Removes mosaic directories of runs that are gone (a SIGKILL cannot clean up).
fn remove_stale_mosaics() {
    for stale in crate::input::left_by_dead_runs(&std::env::temp_dir(), MOSAIC_PREFIX) {
        let _ = std::fs::remove_dir_all(stale);
    }
}

const MOSAIC_PREFIX: &str = "vkterrain-mosaic-";

/// A source under another name (a mosaic is named by its files, not by its temporary
/// VRT, so that the archive's metadata is the same every run), in its errors too: the
/// source, the name, the VRT's path.
struct Named<'a>(&'a dyn Source, String, String);

impl Source for Named<'_> {
    fn name(&self) -> String {
        self.1.clone()
    }
    fn size(&self) -> (usize, usize) {
        self.0.size()
    }
    fn samples(&self) -> crate::input::archive::tile::Samples {
        self.0.samples()
    }
    fn read(&self, x0: i64, z0: i64, nx: usize, nz: usize, stride: usize, out: &mut Vec<f32>) -> Result<(), String> {
        self.0.read(x0, z0, nx, nz, stride, out).map_err(|e| e.replace(&self.2, &self.1))
    }
    fn has_void_mask(&self) -> bool {
        self.0.has_void_mask()
    }
    fn voids(&self, x0: i64, z0: i64, nx: usize, nz: usize, stride: usize, out: &mut Vec<bool>) -> Result<(), String> {
        self.0.voids(x0, z0, nx, nz, stride, out).map_err(|e| e.replace(&self.2, &self.1))
    }
}

/// A private directory for the mosaic's VRT, removed with it.
struct MosaicDir(PathBuf);

impl Drop for MosaicDir {
    fn drop(&mut self) {
        let _ = std::fs::remove_dir_all(&self.0);
    }
}

pub fn prepare(args: &PrepareArgs) -> anyhow::Result<()> {
    let (json, _, _) = prepare_archive(args, Output::File, &|| {})?;
    crate::out!("{}", serde_json::to_string_pretty(&json)?)?;
    Ok(())
}

/// The samples of a raster GDAL reads (its header only); `None` for what it does not
/// read (raw files).
pub(crate) fn raster_size(path: &Path) -> Option<(usize, usize)> {
    WindowReader::open(path).ok().map(|r| (r.raster.width, r.raster.height))
}

/// A terrain file cut into tiles in memory (nothing written), to be drawn from them as an
/// archive is; with the stop signals' handlers the cutting installed (SIGINT, SIGTERM and
/// SIGHUP no longer end the process by themselves): a caller that installs none of its
/// own polls these. What memory holds is the compressed tiles, about what the archive
/// `vkterrain prepare` writes would take on disk.
pub(crate) fn tiles_of_file(
    path: &Path,
    terrain: &crate::app::cli::TerrainArgs,
) -> anyhow::Result<(crate::input::archive::Archive, Stop)> {
    let args = PrepareArgs {
        input: vec![path.to_path_buf()],
        heightmap: None,
        out: PathBuf::new(),
        synthetic: None,
        // The file's frame as the options give it, as the loader would read it.
        frame: terrain.frame,
        raw_size: terrain.raw_size,
        windows: false,
        voids: terrain.voids,
    };
    let (_, archive, stop) = prepare_archive(&args, Output::Memory, &|| {})?;
    Ok((archive.expect("cut in memory"), stop))
}

/// The built-in terrain cut into tiles in memory, framed as the options say.
pub(crate) fn tiles_of_builtin(
    terrain: &crate::app::cli::TerrainArgs,
) -> anyhow::Result<crate::input::archive::Archive> {
    let hf = terrain.load_heightfield(None)?;
    let never = std::sync::atomic::AtomicBool::new(false);
    let (_, archive) = crate::prepare::cut(&InMemory(&hf), &Frame::of(&hf), &|_, _| {}, &never)
        .map_err(|e| InputError(e.to_string()))?;
    Ok(archive)
}

/// Where [`prepare_archive`] puts the tiles: the file `--out` names, or memory (the
/// archive is returned).
#[derive(Clone, Copy, PartialEq, Eq)]
enum Output {
    File,
    Memory,
}

/// [`prepare`] without printing its report: the report, and the archive when it is held
/// in memory. A stop signal ends the process (128 + the signal) once the partial output
/// is gone, after `before_exit` (the caller's own cleaning: exit() runs no destructors).
fn prepare_archive(
    args: &PrepareArgs,
    output: Output,
    before_exit: &dyn Fn(),
) -> anyhow::Result<(serde_json::Value, Option<crate::input::archive::Archive>, Stop)> {
    let to_file = output == Output::File;
    if to_file && args.out.is_dir() {
        return Err(InputError(format!(
            "--out {}: is a directory; name the archive file to write",
            args.out.display()
        ))
        .into());
    }
    // First of all (SIGINT, SIGTERM, SIGHUP), so every run that can clean up does (a
    // signal while a mosaic is read whole takes effect when the read ends).
    let stop = Stop::install();
    remove_stale_mosaics();
    let files = expand_inputs(&args.input)?;
    for input in &files {
        // Before anything opens it: a FIFO would block in open().
        if !crate::input::archive::bytes::is_url(input) {
            crate::input::regular_file(input).map_err(InputError)?;
        }
        if to_file {
            out_is_not_input(input, &args.out)?;
        }
    }
    // Every command that opens archives knows them by their contents, but a name that
    // says another format (`x.png`) would mislead every other program.
    if to_file && !args.out.extension().is_some_and(|e| e.eq_ignore_ascii_case("pmtiles")) {
        return Err(
            InputError(format!("--out {}: an archive is written as a .pmtiles file", args.out.display())).into()
        );
    }
    // A missing directory or a pipe fails now, not after the run.
    let inputs: Vec<(&str, Option<&std::path::Path>)> =
        files.iter().map(|f| ("the input", Some(f.as_path()))).collect();
    crate::app::outputs::check_outputs(&[("--out", to_file.then_some(args.out.as_path()))], &inputs)?;
    // Many files: one GDAL VRT over them, then read like any raster.
    let mut mosaic_dir: Option<MosaicDir> = None;
    let mut mosaic_name: Option<String> = None;
    let input: Option<PathBuf> = match files.as_slice() {
        [] => None,
        [one] if args.input.len() == 1 && !args.input[0].is_dir() => Some(one.clone()),
        many => {
            let dir = std::env::temp_dir().join(format!("{MOSAIC_PREFIX}{}", std::process::id()));
            std::fs::create_dir_all(&dir).map_err(|e| InputError(format!("{}: {e}", dir.display())))?;
            mosaic_dir = Some(MosaicDir(dir.clone()));
            let vrt = dir.join("mosaic.vrt");
            georef::mosaic(many, &vrt).map_err(|e| InputError(e.to_string()))?;
            let name = format!(
                "a mosaic of {} files ({} .. {})",
                many.len(),
                many[0].display(),
                many[many.len() - 1].display()
            );
            eprintln!("vkterrain: note: {name}, placed by their georeferencing");
            mosaic_name = Some(name);
            Some(vrt)
        }
    };
    // A mosaic's errors name it by its files, not by its temporary VRT.
    let named = |e: String| match (&mosaic_name, &input) {
        (Some(name), Some(vrt)) => InputError(e.replace(&vrt.display().to_string(), name)),
        _ => InputError(e),
    };
    let loaded;
    let synthetic;
    let windows;
    let archive;
    let from_archive;
    let (source, frame): (&dyn Source, Frame) = match (&input, args.synthetic) {
        (Some(path), None) if crate::input::archive::Archive::sniff(path) => {
            let mut opened = crate::input::archive::Archive::open(path).map_err(|e| named(e.to_string()))?;
            check_void_mask(&path.display().to_string(), &opened.meta, args.voids)?;
            // With `fill`, the voids stay filled and no mask goes on.
            opened.meta.void_mask &= args.voids == VoidMode::Hole;
            archive = opened;
            let m = &archive.meta;
            let mut georef = m.georef.clone();
            // What this run declares is no longer assumed, nor what the archive said.
            let declared = args.frame.declared();
            georef::drop_overridden(&mut georef.notes, &declared);
            if let Some(s) = args.frame.spacing {
                georef.notes.push(format!("spacing {} x {} m from --spacing, not the archive's", s.x, s.z));
            }
            if let Some(h) = args.frame.height_scale {
                georef.notes.push(format!("height scale {h} m a unit from --height-scale, not the archive's"));
            }
            if let Some(note) = args.frame.heights.and_then(|h| georef::declare_heights(&mut georef, h)) {
                georef.notes.push(note.clone());
                eprintln!("vkterrain: note: {}: {note}", path.display());
            }
            let frame = Frame {
                spacing: args.frame.spacing.map_or(m.spacing, |s| [s.x, s.z]),
                height_scale: args.frame.height_scale.unwrap_or(m.height_scale),
                georef,
                void_samples: m.void_samples,
            };
            eprintln!(
                "vkterrain: note: {}: a prepared archive of {} x {} samples ({}), read tile by tile",
                path.display(),
                m.width,
                m.height,
                m.source
            );
            from_archive = FromArchive::new(&archive);
            (&from_archive, frame)
        }
        (_, Some(_)) if args.voids == VoidMode::Hole => {
            return Err(InputError("--voids hole: the synthetic terrain has no voids".into()).into());
        }
        (_, Some(side)) => {
            synthetic = Synthetic { side: side as usize };
            let frame = Frame {
                spacing: [
                    args.frame.spacing.map_or(Synthetic::SPACING, |s| s.x),
                    args.frame.spacing.map_or(Synthetic::SPACING, |s| s.z),
                ],
                height_scale: args.frame.height_scale.unwrap_or(Synthetic::HEIGHT_SCALE),
                georef: Georef {
                    absolute_heights: args.frame.heights == Some(georef::Heights::Absolute),
                    ..Georef::default()
                },
                void_samples: 0,
            };
            (&synthetic, frame)
        }
        (Some(path), None) if args.voids == VoidMode::Hole && windowed(path, args.windows)? => {
            return Err(named(format!(
                "{}: --voids hole needs the file read whole, to find its voids (not with --windows, nor over {} samples)",
                path.display(),
                IN_MEMORY_SAMPLES
            ))
            .into());
        }
        (Some(path), None) if windowed(path, args.windows)? => {
            let reader = WindowReader::open(path).map_err(|e| named(e.to_string()))?;
            let shown = mosaic_name.clone().unwrap_or_else(|| path.display().to_string());
            // The same known-data-set lookup as the whole read: read window by window, a
            // file keeps the scale its publisher documents.
            let known = georef::known_for_file(&shown, path, &reader.raster).map_err(|e| named(e.to_string()))?;
            let declared = args.frame.declared();
            let scale =
                georef::decide(&shown, &reader.raster, &declared, known, false).map_err(|e| named(e.to_string()))?;
            let (w, h) = (reader.raster.width, reader.raster.height);
            for line in crate::input::describe_frame(&shown, w, h, &scale.georef, scale.spacing, scale.height_scale) {
                eprintln!("vkterrain: note: {line}");
            }
            eprintln!("vkterrain: note: {shown}: read window by window");
            let frame = Frame {
                spacing: [scale.spacing.x, scale.spacing.z],
                height_scale: scale.height_scale,
                georef: scale.georef,
                void_samples: 0,
            };
            windows = Windowed(reader);
            (&windows, frame)
        }
        (Some(path), None) => {
            let opts = LoadOptions {
                spacing: args.frame.spacing,
                height_scale: args.frame.height_scale,
                heights: args.frame.heights,
                raw_size: args.raw_size.map(|(w, h)| (w as usize, h as usize)),
                max_grid_side: None,
                voids: args.voids,
                no_holes: args.voids == VoidMode::Fill,
            };
            loaded = load::load(path, &opts).map_err(|e| named(e.to_string()))?;
            for line in crate::input::describe(&loaded) {
                eprintln!("vkterrain: note: {line}");
            }
            (&InMemory(&loaded), Frame::of(&loaded))
        }
        (None, None) => unreachable!("clap requires an input or --synthetic"),
    };
    let named;
    let source: &dyn Source = match mosaic_name {
        Some(name) => {
            let vrt = input.as_ref().map(|p| p.display().to_string()).unwrap_or_default();
            named = Named(source, name, vrt);
            &named
        }
        None => source,
    };
    if stop.requested() {
        drop(mosaic_dir.take());
        eprintln!("vkterrain: interrupted: {}", if to_file { "no archive written" } else { "nothing written" });
        before_exit();
        std::process::exit(stop.exit_code());
    }
    let (w, h) = source.size();
    let holes = source.has_void_mask();
    crate::prepare::check_frame(&source.name(), &frame, w, h).map_err(|e| InputError(e.to_string()))?;
    let into = if to_file { args.out.display().to_string() } else { "tiles in memory".into() };
    eprintln!("vkterrain: preparing {} ({w} x {h} samples) into {into}", source.name());
    let bar = indicatif::ProgressBar::new(0).with_style(
        indicatif::ProgressStyle::with_template("{elapsed_precise} [{bar:40}] {pos}/{len} windows, ETA {eta}")
            .expect("progress template")
            .progress_chars("=> "),
    );
    // Not on a terminal (a log, CI): a line at every tenth instead of the bar.
    let terminal = std::io::IsTerminal::is_terminal(&std::io::stderr());
    let started = std::time::Instant::now();
    let progress = |done: u64, total: u64| {
        bar.set_length(total);
        bar.set_position(done);
        // Each tenth once, 100% included, whatever the number of windows.
        if !terminal && done > 0 && done * 10 / total > (done - 1) * 10 / total {
            let elapsed = started.elapsed().as_secs_f64();
            let eta = elapsed * (total - done) as f64 / done as f64;
            eprintln!("vkterrain: prepare: {done} of {total} windows, {elapsed:.0} s, about {eta:.0} s to go");
        }
    };
    let result = match output {
        Output::File => crate::prepare::prepare(source, &frame, &args.out, &progress, stop.flag()).map(|r| (r, None)),
        Output::Memory => crate::prepare::cut(source, &frame, &progress, stop.flag()).map(|(r, a)| (r, Some(a))),
    };
    bar.finish_and_clear();
    let (report, archive) = match result {
        Ok(r) => r,
        Err(PrepareError::Source(m)) => return Err(InputError(m).into()),
        Err(PrepareError::Interrupted) => {
            eprintln!("vkterrain: interrupted: {}", if to_file { "no archive written" } else { "nothing written" });
            drop(mosaic_dir.take()); // exit() runs no destructors
            before_exit();
            std::process::exit(stop.exit_code());
        }
        // The output cannot be written (a missing directory, no space, no permission): a
        // problem with what was asked, exit 2 like a bad input.
        Err(e @ PrepareError::Write { .. }) => return Err(InputError(e.to_string()).into()),
    };
    let peak = crate::app::outputs::peak_resident_mb();
    let mut json = serde_json::json!({
        "archive": to_file.then(|| args.out.display().to_string()),
        "report": report,
        "peak_resident_mb": peak,
    });
    let facts = crate::app::outputs::TerrainFacts::of_frame(
        &frame.georef,
        frame.spacing,
        frame.height_scale,
        [w, h],
        frame.void_samples,
    );
    // The archive keeps where the voids were: they can be drawn as holes.
    let voids = if holes { VoidMode::Hole } else { facts.voids };
    crate::app::outputs::TerrainFacts { voids, ..facts }.merge_into(&mut json);
    eprintln!(
        "vkterrain: {}: {} tiles ({} distinct) in {} levels, {:.1} MB ({:.0}% of {:.1} MB uncompressed), {:.1} s, peak resident {}",
        if to_file { format!("wrote {}", args.out.display()) } else { format!("cut {}", source.name()) },
        report.tiles,
        report.distinct_tiles,
        report.levels,
        report.archive_bytes as f64 / 1e6,
        100.0 * report.archive_bytes as f64 / report.raw_bytes.max(1) as f64,
        report.raw_bytes as f64 / 1e6,
        report.seconds,
        peak.map_or("unknown".into(), |mb| format!("{mb:.0} MB")),
    );
    Ok((json, archive, stop))
}

#[derive(clap::Args, Debug)]
pub struct CheckArgs {
    /// The archive to check.
    #[command(flatten)]
    pub input: crate::app::cli::ArchiveInput,
}

/// `vkterrain check`: reads every tile of an archive (directories, sizes, layout,
/// checksums) and prints what it holds and how fast it read, as JSON.
pub fn check(args: &CheckArgs) -> anyhow::Result<()> {
    let started = std::time::Instant::now();
    let archive = crate::input::archive::Archive::open(args.input.path()).map_err(|e| InputError(e.to_string()))?;
    archive.check_layout().map_err(|e| InputError(e.to_string()))?;
    let m = &archive.meta;
    let bar = indicatif::ProgressBar::new(m.tiles().count() as u64);
    let mut tiles = 0u64;
    for (level, tx, tz) in m.tiles() {
        archive.read_tile(level, tx, tz).map_err(|e| InputError(e.to_string()))?;
        tiles += 1;
        bar.inc(1);
    }
    bar.finish_and_clear();
    let seconds = started.elapsed().as_secs_f64();
    let mut json = serde_json::json!({
        "archive": crate::input::archive::bytes::shown(args.input.path()),
        "width": m.width,
        "height": m.height,
        "levels": u32::from(m.top_level) + 1,
        "tiles_checked": tiles,
        "source": m.source,
        "seconds": seconds,
        "ms_per_tile": 1e3 * seconds / tiles.max(1) as f64,
    });
    crate::app::outputs::TerrainFacts::of_meta(m).merge_into(&mut json);
    crate::out!("{}", serde_json::to_string_pretty(&json)?)?;
    eprintln!(
        "vkterrain: {}: {tiles} tiles, every one intact ({seconds:.1} s)",
        crate::input::archive::bytes::shown(args.input.path())
    );
    Ok(())
}
