//! Where `prepare` reads samples from: anything that can hand out a window at a stride.
//! Coordinates outside the true extent repeat the nearest edge sample (as
//! [`Heightfield::embed`] does), so windows may reach past the edges.

use crate::input::archive::tile::Samples;
use crate::lod::heightfield::{HeightFormat, Heightfield};

pub trait Source: Sync {
    /// For messages and the archive's metadata.
    fn name(&self) -> String;
    /// True extent (columns, rows).
    fn size(&self) -> (usize, usize);
    fn samples(&self) -> Samples;
    /// Samples `(x0 + i stride, z0 + j stride)` for `i < nx`, `j < nz`, row-major into
    /// `out` (replaced), raw units.
    fn read(&self, x0: i64, z0: i64, nx: usize, nz: usize, stride: usize, out: &mut Vec<f32>) -> Result<(), String>;
}

/// Clamped coordinates `c0 + i stride` for `i < count` along an axis of `len` samples.
fn axis(c0: i64, count: usize, stride: usize, len: usize) -> impl Iterator<Item = usize> {
    (0..count).map(move |i| (c0 + (i * stride) as i64).clamp(0, len as i64 - 1) as usize)
}

/// A heightfield already in memory (any file the loaders read, voids filled and frame
/// decided as for rendering it directly).
pub struct InMemory<'a>(pub &'a Heightfield);

impl Source for InMemory<'_> {
    fn name(&self) -> String {
        self.0.source.clone()
    }

    fn size(&self) -> (usize, usize) {
        (self.0.width, self.0.height)
    }

    fn samples(&self) -> Samples {
        match self.0.format {
            HeightFormat::Unorm16 => Samples::Unorm16,
            HeightFormat::Float32 => Samples::Float32,
        }
    }

    fn read(&self, x0: i64, z0: i64, nx: usize, nz: usize, stride: usize, out: &mut Vec<f32>) -> Result<(), String> {
        let hf = self.0;
        let gw = hf.grid()[0];
        out.clear();
        for z in axis(z0, nz, stride, hf.height) {
            out.extend(axis(x0, nx, stride, hf.width).map(|x| hf.raw[z * gw + x]));
        }
        Ok(())
    }
}

/// Non-periodic fBm hashed from the sample coordinates (the built-in terrain's
/// generator at any size), quantised to 16 bits of 0.1 m: a terrain of any size made
/// window by window, every tile different.
pub struct Synthetic {
    pub side: usize,
}

impl Synthetic {
    /// Metres per raw unit and per sample.
    pub const HEIGHT_SCALE: f32 = 0.1;
    pub const SPACING: f32 = 30.0;

    pub fn raw(&self, x: usize, z: usize) -> f32 {
        let h = crate::input::procedural::height(x as f32, z as f32, self.side as f32);
        (h / Self::HEIGHT_SCALE).round().clamp(0.0, 65535.0)
    }
}

impl Source for Synthetic {
    fn name(&self) -> String {
        format!("synthetic fBm {0} x {0}", self.side)
    }

    fn size(&self) -> (usize, usize) {
        (self.side, self.side)
    }

    fn samples(&self) -> Samples {
        Samples::Unorm16
    }

    fn read(&self, x0: i64, z0: i64, nx: usize, nz: usize, stride: usize, out: &mut Vec<f32>) -> Result<(), String> {
        out.clear();
        for z in axis(z0, nz, stride, self.side) {
            out.extend(axis(x0, nx, stride, self.side).map(|x| self.raw(x, z)));
        }
        Ok(())
    }
}
