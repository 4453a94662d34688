//! Where heightfields come from: files (PNG, TIFF, raw, SRTM .hgt, ...) and the built-in
//! procedural terrain; and the one check every input file passes before it is read.

pub mod load;
pub mod procedural;

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
