//! `vkterrain prepare`: turns a terrain of any size into a tile archive
//! ([`crate::input::archive`]) window by window, in bounded memory, on every core.
//!
//! One pass over the full-resolution samples, in quadtree (Morton) order: each level-0
//! window (a tile's `T + 1` samples a side and a one-sample border) becomes a level-0
//! tile and yields, for every coarser level `l`, the exact deviation `D_l` of the
//! groups inside it (or, for groups larger than the window, the window's share of their
//! maximum: `L_l` over a sample needs only its quad's four corners, which the lattice of
//! window corners read up front holds). A level-`t` tile gathers its four children's
//! vertices (every second one), its own border (one strided read per side), and its
//! `D_t`, completed from its children. Memory: four nodes per level of the recursion and
//! per thread, a few MB, whatever the terrain's size.

pub mod source;

use crate::input::archive::tile::{self, Samples, Tile};
use crate::input::archive::{pmtiles, Archive, ArchiveWriter, Meta, ARCHIVE_VERSION, TILE_QUADS};
use crate::lod::deviation::square_deviation;
use crate::lod::heightfield::Georef;
pub use source::Source;
use std::collections::HashSet;
use std::path::Path;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::Mutex;

/// What the archive says about the world frame (from the input's georeferencing).
#[derive(Clone, Debug)]
pub struct Frame {
    pub spacing: [f32; 2],
    pub height_scale: f32,
    pub georef: Georef,
    pub void_samples: usize,
}

impl Frame {
    /// The frame of a heightfield already loaded (its voids filled, its frame decided).
    pub fn of(hf: &crate::lod::heightfield::Heightfield) -> Frame {
        Frame {
            spacing: [hf.spacing.x, hf.spacing.z],
            height_scale: hf.height_scale,
            georef: hf.georef.clone(),
            void_samples: hf.void_samples,
        }
    }
}

/// What a run made, for the report.
#[derive(Clone, Debug, Default, serde::Serialize)]
pub struct Prepared {
    pub width: usize,
    pub height: usize,
    pub levels: u32,
    pub tiles: u64,
    /// Tiles whose heights and deviations differ from every other tile's.
    pub distinct_tiles: u64,
    pub archive_bytes: u64,
    /// Payload bytes before compression.
    pub raw_bytes: u64,
    pub seconds: f64,
}

#[derive(Debug, thiserror::Error)]
pub enum PrepareError {
    #[error("{0}")]
    Source(String),
    #[error("{path}: {source}")]
    Write { path: String, source: std::io::Error },
    #[error("interrupted: no archive written")]
    Interrupted,
}

/// A finished subtree, as its parent needs it.
struct Node {
    /// The tile's own LOD vertices, `(T + 1)^2`, no border.
    vertices: Vec<f32>,
    /// For each level `l` above the tile's, `D_l` of the groups inside its square
    /// (`side^2`, side `max(1, T 2^t / 2^l)`; at side 1 possibly a share of a larger
    /// group's maximum).
    deviation: Vec<Vec<f32>>,
}

struct Run<'a> {
    source: &'a dyn Source,
    samples: Samples,
    width: usize,
    height: usize,
    top: u8,
    /// `n` of the covered square.
    n: u32,
    /// Window corners: sample `(i T, j T)` at `i + j (2^top + 1)`.
    lattice: Vec<f32>,
    writer: Mutex<ArchiveWriter>,
    /// The archive's name in messages.
    out: &'a str,
    seen: Mutex<HashSet<u64>>,
    raw_bytes: AtomicU64,
    leaves_done: AtomicU64,
    progress: &'a (dyn Fn(u64, u64) + Sync),
    leaves_total: u64,
    stop: &'a AtomicBool,
    height_scale: f32,
    /// Lowest and highest raw height read so far (every sample is in some leaf window).
    range: Mutex<[f32; 2]>,
    /// Whether tiles keep which of their vertices are voids ([`Source::has_void_mask`]).
    holes: bool,
}

/// The largest world coordinate an archive holds (extent and heights): what the
/// renderer accepts, so that every archive written can be drawn.
const MAX_WORLD: f64 = crate::lod::heightfield::MAX_WORLD as f64;

/// Spacing, height scale and extent are finite, positive and within [`MAX_WORLD`].
pub fn check_frame(name: &str, frame: &Frame, width: usize, height: usize) -> Result<(), PrepareError> {
    let [sx, sz] = frame.spacing.map(f64::from);
    let hs = f64::from(frame.height_scale);
    let fine = |v: f64| v.is_finite() && v > 0.0;
    if !(fine(sx) && fine(sz) && fine(hs)) {
        return Err(PrepareError::Source(format!(
            "{name}: spacing {sx:e} x {sz:e} and height scale {hs:e} must be finite and greater than 0"
        )));
    }
    let extent = [sx * (width - 1) as f64, sz * (height - 1) as f64];
    if extent.iter().any(|e| *e > MAX_WORLD) || hs > MAX_WORLD {
        return Err(PrepareError::Source(format!(
            "{name}: {width} x {height} samples at spacing {sx:e} x {sz:e} span {:e} x {:e} world units, height scale {hs:e}: beyond {:e} world units (single-precision positions; give --spacing or --height-scale)",
            extent[0], extent[1], crate::lod::heightfield::MAX_WORLD
        )));
    }
    Ok(())
}

/// Prepares `source` into an archive at `out` (see the module's documentation).
/// `progress(done, total)` is called as level-0 windows finish; `stop` interrupts (the
/// partial file is removed).
pub fn prepare(
    source: &dyn Source,
    frame: &Frame,
    out: &Path,
    progress: &(dyn Fn(u64, u64) + Sync),
    stop: &AtomicBool,
) -> Result<Prepared, PrepareError> {
    let started = std::time::Instant::now();
    let io = |source| PrepareError::Write { path: out.display().to_string(), source };
    let writer = ArchiveWriter::create(out).map_err(io)?;
    let (mut prepared, mut meta, writer) =
        write_tiles(source, frame, writer, &out.display().to_string(), progress, stop)?;
    prepared.archive_bytes = writer.finish(&mut meta).map_err(io)?;
    prepared.seconds = started.elapsed().as_secs_f64();
    Ok(prepared)
}

/// Cuts `source` into an archive held in memory (nothing is written): how a terrain file
/// is drawn from tiles like any archive. `progress` and `stop` as for [`prepare`].
pub fn cut(
    source: &dyn Source,
    frame: &Frame,
    progress: &(dyn Fn(u64, u64) + Sync),
    stop: &AtomicBool,
) -> Result<(Prepared, Archive), PrepareError> {
    let started = std::time::Instant::now();
    let io = |source| PrepareError::Write { path: "memory".into(), source };
    let (mut prepared, mut meta, writer) =
        write_tiles(source, frame, ArchiveWriter::memory(), "memory", progress, stop)?;
    let bytes = writer.finish_in_memory(&mut meta).map_err(io)?;
    prepared.archive_bytes = bytes.len() as u64;
    prepared.seconds = started.elapsed().as_secs_f64();
    let archive = Archive::in_memory(Path::new(&source.name()), bytes).map_err(|e| {
        PrepareError::Source(format!("{}: the tiles cut in memory do not read back: {e}", source.name()))
    })?;
    Ok((prepared, archive))
}

/// Every tile of `source` into `writer` (named `out` in messages); the report (less the
/// archive's size), the metadata, and the writer to finish.
fn write_tiles(
    source: &dyn Source,
    frame: &Frame,
    writer: ArchiveWriter,
    out: &str,
    progress: &(dyn Fn(u64, u64) + Sync),
    stop: &AtomicBool,
) -> Result<(Prepared, Meta, ArchiveWriter), PrepareError> {
    let (width, height) = source.size();
    if width < 3 || height < 3 {
        return Err(PrepareError::Source(format!(
            "{}: {width} x {height} is too small: a terrain needs at least 3 x 3 samples",
            source.name()
        )));
    }
    check_frame(&source.name(), frame, width, height)?;
    let top = Meta::top_level_for(width, height, TILE_QUADS);
    let n = TILE_QUADS.trailing_zeros() + u32::from(top);
    let corners = (1usize << top) + 1;
    let mut lattice = Vec::new();
    source.read(0, 0, corners, corners, TILE_QUADS, &mut lattice).map_err(PrepareError::Source)?;
    let span0 = TILE_QUADS;
    let leaves_total = ((width - 1).div_ceil(span0) * (height - 1).div_ceil(span0)) as u64;
    let run = Run {
        source,
        samples: source.samples(),
        width,
        height,
        top,
        n,
        lattice,
        writer: Mutex::new(writer),
        out,
        seen: Mutex::new(HashSet::new()),
        raw_bytes: AtomicU64::new(0),
        leaves_done: AtomicU64::new(0),
        progress,
        leaves_total,
        stop,
        height_scale: frame.height_scale,
        range: Mutex::new([f32::INFINITY, f32::NEG_INFINITY]),
        holes: source.has_void_mask(),
    };
    run.build(top, 0, 0)?;
    let meta = Meta {
        kind: "vkterrain terrain archive".into(),
        version: ARCHIVE_VERSION,
        width,
        height,
        tile_quads: TILE_QUADS,
        top_level: top,
        samples: match run.samples {
            Samples::Unorm16 => "unorm16",
            Samples::Float32 => "float32",
        }
        .into(),
        spacing: frame.spacing,
        height_scale: frame.height_scale,
        georef: frame.georef.clone(),
        void_samples: frame.void_samples,
        source: source.name(),
        tiles: 0,
        raw_range: Some(run.range.into_inner().expect("range lock")),
        void_mask: run.holes,
    };
    let prepared = Prepared {
        width,
        height,
        levels: u32::from(top) + 1,
        tiles: meta.tiles().count() as u64,
        distinct_tiles: run.seen.into_inner().expect("seen lock").len() as u64,
        archive_bytes: 0,
        raw_bytes: run.raw_bytes.into_inner(),
        seconds: 0.0,
    };
    Ok((prepared, meta, run.writer.into_inner().expect("writer lock")))
}

impl Run<'_> {
    /// Does tile `(level, tx, tz)` touch the true extent (is it stored)?
    fn stored(&self, level: u8, tx: u32, tz: u32) -> bool {
        let span = (TILE_QUADS as u64) << level;
        (tx as u64 * span) < self.width as u64 - 1 && (tz as u64 * span) < self.height as u64 - 1
    }

    fn build(&self, level: u8, tx: u32, tz: u32) -> Result<Node, PrepareError> {
        if self.stop.load(Ordering::Relaxed) {
            return Err(PrepareError::Interrupted);
        }
        if !self.stored(level, tx, tz) {
            return self.outside(level, tx, tz);
        }
        if level == 0 {
            return self.leaf(tx, tz);
        }
        let child = |i: u32, j: u32| self.build(level - 1, 2 * tx + i, 2 * tz + j);
        let ((c00, c10), (c01, c11)) =
            rayon::join(|| rayon::join(|| child(0, 0), || child(1, 0)), || rayon::join(|| child(0, 1), || child(1, 1)));
        let children = [c00?, c10?, c01?, c11?];
        let t = TILE_QUADS;
        // Every second vertex of the children, the shared middle row and column once.
        let mut vertices = vec![0.0f32; (t + 1) * (t + 1)];
        for b in 0..=t {
            for a in 0..=t {
                let (i, j) = ((2 * a / t).min(1), (2 * b / t).min(1));
                let c = &children[i + 2 * j];
                vertices[b * (t + 1) + a] = c.vertices[(2 * b - j * t) * (t + 1) + (2 * a - i * t)];
            }
        }
        // Children hold levels `level..=n`, in order.
        let deviation: Vec<Vec<f32>> = (0..children[0].deviation.len())
            .map(|k| {
                let parts: Vec<&[f32]> = children.iter().map(|c| c.deviation[k].as_slice()).collect();
                merge(&parts, side_at(level, u32::from(level) + k as u32))
            })
            .collect();
        let (own, above) = deviation.split_first().expect("a level above the leaves has its own D");
        if level == self.top {
            // The top tile holds the rest of the pyramid, up to the one group of LOD n.
            self.write(level, tx, tz, &vertices, deviation.concat())?;
            return Ok(Node { vertices, deviation: Vec::new() });
        }
        self.write(level, tx, tz, &vertices, own.clone())?;
        Ok(Node { vertices, deviation: above.to_vec() })
    }

    /// A tile beyond the true extent (not stored): its vertices repeat the edge, its
    /// groups are never drawn (`D = 0`, as in [`crate::lod::deviation`]).
    fn outside(&self, level: u8, tx: u32, tz: u32) -> Result<Node, PrepareError> {
        let t = TILE_QUADS;
        let step = 1usize << level;
        let mut vertices = Vec::new();
        let (x0, z0) = (tx as i64 * (t * step) as i64, tz as i64 * (t * step) as i64);
        self.source.read(x0, z0, t + 1, t + 1, step, &mut vertices).map_err(PrepareError::Source)?;
        let deviation = (u32::from(level) + 1..=self.n).map(|l| vec![0.0; side_at(level, l).pow(2)]).collect();
        Ok(Node { vertices, deviation })
    }

    fn leaf(&self, tx: u32, tz: u32) -> Result<Node, PrepareError> {
        let t = TILE_QUADS;
        let w = t + 3;
        let (x0, z0) = ((tx as usize * t) as i64, (tz as usize * t) as i64);
        let mut window = Vec::new();
        self.source.read(x0 - 1, z0 - 1, w, w, 1, &mut window).map_err(PrepareError::Source)?;
        let world = |h: f32| f64::from(h) * f64::from(self.height_scale);
        // NaN is out of range too.
        if let Some(i) = window.iter().position(|h| world(*h).is_nan() || world(*h).abs() > MAX_WORLD) {
            // The window's border beyond the extent repeats the edge sample: that one's place.
            let x = (x0 - 1 + (i % w) as i64).clamp(0, self.width as i64 - 1);
            let z = (z0 - 1 + (i / w) as i64).clamp(0, self.height as i64 - 1);
            return Err(PrepareError::Source(format!(
                "{}: the sample at column {x}, row {z} is {} ({:e} world units with height scale {:e}): beyond {:e} world units (single-precision positions)",
                self.source.name(),
                window[i],
                world(window[i]),
                self.height_scale,
                crate::lod::heightfield::MAX_WORLD
            )));
        }
        // The window's samples beyond the extent repeat its edge: real samples all.
        let (lo, hi) = window.iter().fold((f32::INFINITY, f32::NEG_INFINITY), |(a, b), &h| (a.min(h), b.max(h)));
        {
            let mut r = self.range.lock().expect("range lock");
            *r = [r[0].min(lo), r[1].max(hi)];
        }
        // Row `z` (tile-local, -1..=T+1) of the window from column `x`.
        let row = |x: i64, z: i64, count: usize| &window[(z + 1) as usize * w + (x + 1) as usize..][..count];
        let mut deviation = Vec::with_capacity(self.n as usize);
        for l in 1..=self.n {
            let s = 1i64 << l;
            let g = side_at(0, l);
            let mut level = vec![0.0f32; g * g];
            for (k, d) in level.iter_mut().enumerate() {
                // Groups of this level inside the window, or the one group it lies in.
                let (qx, qz) =
                    if g > 1 { (((k % g) as i64) * s, ((k / g) as i64) * s) } else { (-(x0 % s), -(z0 % s)) };
                if x0 + qx >= self.width as i64 - 1 || z0 + qz >= self.height as i64 - 1 {
                    continue;
                }
                let corners = [(qx, qz), (qx + s, qz), (qx, qz + s), (qx + s, qz + s)]
                    .map(|(x, z)| self.corner(x0, z0, x, z, &window));
                let span = if g > 1 { s } else { t as i64 };
                let (sx, sz) = if g > 1 { (qx, qz) } else { (0, 0) };
                *d = square_deviation(row, sx, sz, span, corners, (qx, qz), s);
            }
            deviation.push(level);
        }
        let vertices: Vec<f32> = (0..=t).flat_map(|j| row(0, j as i64, t + 1).to_vec()).collect();
        // A terrain of one tile: its pyramid (LOD 1 to n) is stored with it.
        let own = if self.top == 0 { std::mem::take(&mut deviation).concat() } else { Vec::new() };
        self.write_tile(0, tx, tz, window, own)?;
        let done = self.leaves_done.fetch_add(1, Ordering::Relaxed) + 1;
        (self.progress)(done, self.leaves_total);
        Ok(Node { vertices, deviation })
    }

    /// Height of the tile-local sample `(x, z)` of window `(x0, z0)`: from the window
    /// when inside it, else a lattice corner (a coarser group's corner).
    fn corner(&self, x0: i64, z0: i64, x: i64, z: i64, window: &[f32]) -> f32 {
        let w = (TILE_QUADS + 3) as i64;
        if (-1..w - 1).contains(&x) && (-1..w - 1).contains(&z) {
            return window[((z + 1) * w + x + 1) as usize];
        }
        let side = (1usize << self.top) + 1;
        let (gx, gz) = ((x0 + x) as usize / TILE_QUADS, (z0 + z) as usize / TILE_QUADS);
        self.lattice[gz * side + gx]
    }

    /// A tile at `level` above 0: its vertices and the border read from the source.
    fn write(&self, level: u8, tx: u32, tz: u32, vertices: &[f32], own: Vec<f32>) -> Result<(), PrepareError> {
        let t = TILE_QUADS;
        let side = t + 3;
        let step = 1i64 << level;
        let (x0, z0) = (tx as i64 * t as i64 * step, tz as i64 * t as i64 * step);
        let mut heights = vec![0.0f32; side * side];
        for b in 0..=t {
            heights[(b + 1) * side + 1..][..t + 1].copy_from_slice(&vertices[b * (t + 1)..][..t + 1]);
        }
        let mut strip = Vec::new();
        for (z, zi) in [(z0 - step, 0usize), (z0 + (t as i64 + 1) * step, side - 1)] {
            self.source.read(x0 - step, z, side, 1, step as usize, &mut strip).map_err(PrepareError::Source)?;
            heights[zi * side..][..side].copy_from_slice(&strip);
        }
        for (x, xi) in [(x0 - step, 0usize), (x0 + (t as i64 + 1) * step, side - 1)] {
            self.source.read(x, z0, 1, t + 1, step as usize, &mut strip).map_err(PrepareError::Source)?;
            for (b, &h) in strip.iter().enumerate() {
                heights[(b + 1) * side + xi] = h;
            }
        }
        self.write_tile(level, tx, tz, heights, own)
    }

    fn write_tile(
        &self,
        level: u8,
        tx: u32,
        tz: u32,
        heights: Vec<f32>,
        deviation: Vec<f32>,
    ) -> Result<(), PrepareError> {
        let side = TILE_QUADS + 3;
        // Which of the tile's vertices (its border included) are voids: the samples its
        // heights are, read at its stride. Only a tile with one keeps a mask.
        let voids = if self.holes {
            let step = 1i64 << level;
            let span = TILE_QUADS as i64 * step;
            let mut mask = Vec::new();
            let (x0, z0) = (i64::from(tx) * span - step, i64::from(tz) * span - step);
            self.source.voids(x0, z0, side, side, step as usize, &mut mask).map_err(PrepareError::Source)?;
            mask.contains(&true).then_some(mask)
        } else {
            None
        };
        let tile = Tile { level, tx, tz, side, heights, deviation, voids };
        let payload = tile::encode(&tile, self.samples);
        self.raw_bytes.fetch_add(payload.len() as u64, Ordering::Relaxed);
        let compressed = pmtiles::zstd(&payload);
        let key = {
            use std::hash::{BuildHasher, Hasher};
            let mut h = foldhash::quality::FixedState::with_seed(27).build_hasher();
            // The heights and deviations only: the header names the tile.
            h.write(&payload[24..]);
            h.finish()
        };
        self.seen.lock().expect("seen lock").insert(key);
        let io = |source| PrepareError::Write { path: self.out.to_string(), source };
        self.writer.lock().expect("writer lock").add(self.top, level, tx, tz, &compressed).map_err(io)?;
        Ok(())
    }
}

/// Groups a side of level `l` in a tile of level `t` (at least 1).
pub fn side_at(t: u8, l: u32) -> usize {
    (TILE_QUADS << t >> l.min(TILE_QUADS.trailing_zeros() + u32::from(t))).max(1)
}

/// Four children's `D` arrays of one level (order 00, 10, 01, 11) as their parent's,
/// `side` groups a side: side by side where a group is no larger than a child, else
/// (side 1) the maximum of the four shares of the one group.
fn merge(parts: &[&[f32]], side: usize) -> Vec<f32> {
    let len = parts[0].len();
    let g = side / 2;
    if side == 1 {
        return vec![parts.iter().map(|p| p[0]).fold(0.0, f32::max)];
    }
    debug_assert_eq!(g * g, len);
    let mut out = vec![0.0f32; 4 * len];
    for (c, p) in parts.iter().enumerate() {
        let (i, j) = (c % 2, c / 2);
        for b in 0..g {
            out[(j * g + b) * 2 * g + i * g..][..g].copy_from_slice(&p[b * g..][..g]);
        }
    }
    out
}
