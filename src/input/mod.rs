//! Where heightfields come from: files (PNG, TIFF, raw, SRTM .hgt, ...) and the built-in
//! procedural terrain; and the one check every input file passes before it is read.

pub mod archive;
pub mod georef;
pub mod load;
pub mod procedural;

use crate::lod::heightfield::Heightfield;
use std::fs::Metadata;
use std::path::Path;

/// What is wrong with reading a file of this kind, if anything: a FIFO or a character
/// device would block the reader forever, and a directory fails later with a less
/// helpful message.
pub fn not_a_file(meta: &Metadata) -> Option<&'static str> {
    if meta.is_dir() {
        Some("is a directory, not a file")
    } else if !meta.is_file() {
        Some("not a regular file (a FIFO, socket or device): reading it might never end")
    } else {
        None
    }
}

/// The entries of `dir` named `PREFIX<pid>` or `PREFIX<pid>-...` whose process is gone:
/// what a run killed by SIGKILL or a crash left behind (a live PID's are another run's).
pub fn left_by_dead_runs(dir: &Path, prefix: &str) -> Vec<std::path::PathBuf> {
    let Ok(entries) = std::fs::read_dir(dir) else { return Vec::new() };
    entries
        .flatten()
        .filter(|entry| {
            let name = entry.file_name();
            let pid = name
                .to_str()
                .and_then(|n| n.strip_prefix(prefix))
                .and_then(|p| p.split('-').next().and_then(|d| d.parse::<u32>().ok()));
            pid.is_some_and(|pid| pid != std::process::id() && !Path::new(&format!("/proc/{pid}")).exists())
        })
        .map(|entry| entry.path())
        .collect()
}

/// Checks that `path` (through symbolic links) is a regular file before anything reads
/// it; the error names the path.
pub fn regular_file(path: &Path) -> Result<Metadata, String> {
    let meta = std::fs::metadata(path).map_err(|e| format!("{}: {e}", path.display()))?;
    match not_a_file(&meta) {
        Some(problem) => Err(format!("{}: {problem}", path.display())),
        None => Ok(meta),
    }
}

/// What was read at load, in lines for the terminal: size, CRS and origin, how spacing
/// and heights were decided, voids.
pub fn describe(hf: &Heightfield) -> Vec<String> {
    let mut lines = describe_frame(&hf.source, hf.width, hf.height, &hf.georef, hf.spacing, hf.height_scale);
    if hf.void_samples > 0 {
        let share = 100.0 * hf.void_samples as f64 / (hf.width * hf.height) as f64;
        lines.push(format!(
            "{}: {} void (nodata) samples ({share:.1}%) filled smoothly (Laplace){}",
            hf.source,
            hf.void_samples,
            if hf.void_mask.is_some() { ", drawn as holes" } else { "" }
        ));
    }
    lines
}

/// The lines of [`describe`] about the frame, for inputs not (yet) in memory.
pub fn describe_frame(
    source: &str,
    width: usize,
    height: usize,
    g: &crate::lod::heightfield::Georef,
    spacing: crate::lod::heightfield::Spacing,
    height_scale: f32,
) -> Vec<String> {
    let mut lines = vec![match &g.crs {
        Some(crs) => format!(
            "{source}: {width} x {height} samples, {crs}, first sample at {:.6}, {:.6}",
            g.origin[0], g.origin[1]
        ),
        None => format!("{source}: {width} x {height} samples, no CRS"),
    }];
    lines.extend(g.notes.iter().map(|n| format!("{source}: {n}")));
    lines.push(format!(
        "{source}: world frame {} x {} m a sample, {height_scale} m a height unit",
        spacing.x, spacing.z
    ));
    lines
}
