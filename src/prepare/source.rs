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
    /// Whether the source says which samples were voids, for the archive to keep
    /// (`--voids hole`); without it [`Source::voids`] is never asked.
    fn has_void_mask(&self) -> bool {
        false
    }
    /// Which of the samples [`Source::read`] gives for the same arguments were voids; at
    /// a stride `s` above 1, whether a void lies within `s - 1` samples of each along
    /// both axes (a coarser tile's flag covers its vertex's neighbourhood, so that a
    /// block holding a void is known from any tile that serves it).
    fn voids(&self, x0: i64, z0: i64, nx: usize, nz: usize, stride: usize, out: &mut Vec<bool>) -> Result<(), String> {
        let _ = (x0, z0, stride);
        out.clear();
        out.resize(nx * nz, false);
        Ok(())
    }
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

    fn has_void_mask(&self) -> bool {
        self.0.void_mask.is_some()
    }

    fn voids(&self, x0: i64, z0: i64, nx: usize, nz: usize, stride: usize, out: &mut Vec<bool>) -> Result<(), String> {
        let hf = self.0;
        out.clear();
        // Each sample's neighbourhood, clamped to the true extent. Voids are few: the
        // scan reads every sample of a coarse tile's area about four times (8193^2:
        // a few seconds over every level).
        let r = stride as i64 - 1;
        let near = |c: usize, len: usize| (c as i64 - r).max(0)..=(c as i64 + r).min(len as i64 - 1);
        for z in axis(z0, nz, stride, hf.height) {
            out.extend(
                axis(x0, nx, stride, hf.width)
                    .map(|x| near(z, hf.height).any(|zz| near(x, hf.width).any(|xx| hf.is_hole(xx, zz)))),
            );
        }
        Ok(())
    }
}

/// Non-periodic fBm hashed from the sample coordinates (the built-in terrain's
/// generator), quantised to 16 bits of 0.1 m: a terrain of any size made window by
/// window, every tile different. Its features keep the built-in terrain's sizes (ranges
/// tens of km across at 30 m, detail down to a few samples) however large the side, as
/// a real elevation model's do: scaled with the side, a 65537^2 terrain would be smooth
/// over 25 samples and light to stream.
pub struct Synthetic {
    pub side: usize,
}

impl Synthetic {
    /// Metres per raw unit and per sample.
    pub const HEIGHT_SCALE: f32 = 0.1;
    pub const SPACING: f32 = 30.0;
    /// The side whose feature sizes every synthetic terrain has (the built-in terrain's).
    pub const FEATURE_SIDE: f32 = 2049.0;

    pub fn raw(&self, x: usize, z: usize) -> f32 {
        let h = crate::input::procedural::height(x as f32, z as f32, Self::FEATURE_SIDE);
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

/// A prepared archive read tile by tile (re-preparing it, or an archive of any size as
/// an input): memory follows the windows and a small cache of decoded tiles, not the
/// terrain. A strided read takes its samples from the coarsest tiles that hold them.
pub struct FromArchive<'a> {
    pub archive: &'a crate::input::archive::Archive,
    tiles: std::sync::Mutex<TileLru>,
}

/// Recently used decoded tiles (windows in Morton order share most of theirs).
#[derive(Default)]
struct TileLru {
    tiles: std::collections::HashMap<(u8, u32, u32), (std::sync::Arc<crate::input::archive::tile::Tile>, u64)>,
    clock: u64,
}

impl<'a> FromArchive<'a> {
    /// Decoded tiles kept: a window and its neighbours at every level, a few times over.
    pub const CACHED_TILES: usize = 64;

    pub fn new(archive: &'a crate::input::archive::Archive) -> Self {
        FromArchive { archive, tiles: Default::default() }
    }

    fn tile(&self, level: u8, tx: u32, tz: u32) -> Result<std::sync::Arc<crate::input::archive::tile::Tile>, String> {
        let key = (level, tx, tz);
        {
            let mut lru = self.tiles.lock().expect("tile cache");
            lru.clock += 1;
            let now = lru.clock;
            if let Some((tile, used)) = lru.tiles.get_mut(&key) {
                *used = now;
                return Ok(tile.clone());
            }
        }
        // Read and decode outside the lock (the workers read in parallel).
        let tile = self
            .archive
            .read_tile(level, tx, tz)
            .map_err(|e| e.to_string())?
            .ok_or_else(|| format!("{}: missing", self.archive.tile_name(level, tx, tz)))?;
        let tile = std::sync::Arc::new(tile);
        let mut lru = self.tiles.lock().expect("tile cache");
        if lru.tiles.len() >= Self::CACHED_TILES {
            if let Some(oldest) = lru.tiles.iter().min_by_key(|(_, (_, used))| *used).map(|(k, _)| *k) {
                lru.tiles.remove(&oldest);
            }
        }
        let now = lru.clock;
        lru.tiles.insert(key, (tile.clone(), now));
        Ok(tile)
    }
}

impl Source for FromArchive<'_> {
    fn name(&self) -> String {
        self.archive.path().display().to_string()
    }

    fn size(&self) -> (usize, usize) {
        (self.archive.meta.width, self.archive.meta.height)
    }

    fn samples(&self) -> Samples {
        self.archive.meta.sample_format().expect("checked at open")
    }

    fn read(&self, x0: i64, z0: i64, nx: usize, nz: usize, stride: usize, out: &mut Vec<f32>) -> Result<(), String> {
        out.clear();
        out.reserve(nx * nz);
        self.each_sample(x0, z0, nx, nz, stride, |tile, i| out.push(tile.heights[i]))
    }

    fn has_void_mask(&self) -> bool {
        self.archive.meta.void_mask
    }

    fn voids(&self, x0: i64, z0: i64, nx: usize, nz: usize, stride: usize, out: &mut Vec<bool>) -> Result<(), String> {
        out.clear();
        out.reserve(nx * nz);
        // A tile without a mask has no voids.
        self.each_sample(x0, z0, nx, nz, stride, |tile, i| out.push(tile.voids.as_ref().is_some_and(|v| v[i])))
    }
}

impl FromArchive<'_> {
    /// Calls `f(tile, index)` for each sample [`Source::read`] gives, in its order: the
    /// tile holding it and its index among the tile's `side^2` values.
    fn each_sample(
        &self,
        x0: i64,
        z0: i64,
        nx: usize,
        nz: usize,
        stride: usize,
        mut f: impl FnMut(&crate::input::archive::tile::Tile, usize),
    ) -> Result<(), String> {
        let m = &self.archive.meta;
        let (w, h) = (m.width, m.height);
        // The coarsest level whose vertices are every `stride`-th sample.
        let level = (stride.trailing_zeros() as u8).min(m.top_level);
        let mut current: Option<((u8, u32, u32), std::sync::Arc<crate::input::archive::tile::Tile>)> = None;
        for z in axis(z0, nz, stride, h) {
            for x in axis(x0, nx, stride, w) {
                // Clamped edge samples may lie off the coarse lattice: those come from
                // level 0.
                let step = 1usize << level;
                let l = if x % step == 0 && z % step == 0 { level } else { 0 };
                let span = m.tile_quads << l;
                let [ntx, ntz] = m.tiles_at(l);
                let (tx, tz) = ((x / span).min(ntx as usize - 1), (z / span).min(ntz as usize - 1));
                let key = (l, tx as u32, tz as u32);
                if current.as_ref().is_none_or(|(k, _)| *k != key) {
                    current = Some((key, self.tile(l, tx as u32, tz as u32)?));
                }
                let tile = &current.as_ref().expect("just set").1;
                let (i, j) = ((x - tx * span) >> l, (z - tz * span) >> l);
                f(tile, (j + 1) * tile.side + i + 1);
            }
        }
        Ok(())
    }
}
