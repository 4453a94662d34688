//! Where `prepare` reads samples from: anything that can hand out a window at a stride.
//! Coordinates outside the true extent repeat the nearest edge sample (as
//! [`Heightfield::embed`] does), so windows may reach past the edges.

use crate::input::archive::tile::Samples;
use crate::input::georef::WindowReader;
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

/// A file read window by window through GDAL ([`WindowReader`]): memory follows the
/// windows, not the file.
pub struct Windowed(pub WindowReader);

impl Source for Windowed {
    fn name(&self) -> String {
        self.0.path().display().to_string()
    }

    fn size(&self) -> (usize, usize) {
        (self.0.raster.width, self.0.raster.height)
    }

    fn samples(&self) -> Samples {
        match self.0.raster.format {
            HeightFormat::Unorm16 => Samples::Unorm16,
            HeightFormat::Float32 => Samples::Float32,
        }
    }

    fn read(&self, x0: i64, z0: i64, nx: usize, nz: usize, stride: usize, out: &mut Vec<f32>) -> Result<(), String> {
        let (w, h) = self.size();
        let xs: Vec<usize> = axis(x0, nx, stride, w).collect();
        let zs: Vec<usize> = axis(z0, nz, stride, h).collect();
        let (xa, xb) = (xs[0], xs[nx - 1]);
        out.clear();
        out.reserve(nx * nz);
        if stride == 1 {
            // One box, the clamped margin repeated from it.
            let (za, zb) = (zs[0], zs[nz - 1]);
            let boxed = self.0.read(xa, za, xb, zb)?;
            let bw = xb - xa + 1;
            for &z in &zs {
                out.extend(xs.iter().map(|&x| boxed[(z - za) * bw + (x - xa)]));
            }
            return Ok(());
        }
        // Strided: each distinct row once, the span of its columns at full resolution.
        let mut last: Option<(usize, Vec<f32>)> = None;
        for &z in &zs {
            if last.as_ref().is_none_or(|(lz, _)| *lz != z) {
                let row = self.0.read(xa, z, xb, z)?;
                last = Some((z, row));
            }
            let row = &last.as_ref().expect("just read").1;
            out.extend(xs.iter().map(|&x| row[x - xa]));
        }
        Ok(())
    }
}
