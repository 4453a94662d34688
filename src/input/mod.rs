//! Where heightfields come from: files (PNG, TIFF, raw, SRTM .hgt, ...) and the built-in
//! procedural terrain.

pub mod load;
pub mod procedural;
