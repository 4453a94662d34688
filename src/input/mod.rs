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
    let g = &hf.georef;
    let mut lines = vec![match &g.crs {
        Some(crs) => format!(
            "{}: {} x {} samples, {crs}, first sample at {:.6}, {:.6}",
            hf.source, hf.width, hf.height, g.origin[0], g.origin[1]
        ),
        None => format!("{}: {} x {} samples, no CRS", hf.source, hf.width, hf.height),
    }];
    lines.extend(g.notes.iter().map(|n| format!("{}: {n}", hf.source)));
    lines.push(format!(
        "{}: world frame {} x {} m a sample, {} m a height unit",
        hf.source, hf.spacing.x, hf.spacing.z, hf.height_scale
    ));
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
