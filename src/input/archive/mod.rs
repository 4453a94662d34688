//! The terrain archive (SPEC section 8): a quadtree of tiles in one PMTiles v3 file
//! ([`pmtiles`]), each tile a versioned, checksummed payload ([`tile`]), zstd-compressed. Written by
//! `vkterrain prepare` ([`crate::prepare`]), read here: the metadata says what the
//! terrain is (size, frame, georeferencing) and every tile read is checked.
//!
//! The quadtree: level-0 tiles hold every sample of `T x T` quads (`T + 1` vertices a
//! side, borders shared), level `t` tiles every `2^t`-th sample of `T 2^t` samples; the
//! top level `L` is one tile over a square of `T 2^L + 1` samples (PMTiles zoom
//! `L - t`, x along columns, y along rows). Tiles wholly outside the true extent are not
//! stored; samples outside it in a stored tile repeat the nearest edge sample, as
//! [`Heightfield::embed`] does.

pub mod bytes;
pub mod pmtiles;
pub mod tile;

use crate::lod::heightfield::{Georef, HeightFormat, Heightfield, HeightfieldError, Spacing};
use pmtiles::{Entry, Header};
use std::collections::HashMap;
use std::fs::File;
use std::io::{Seek, SeekFrom, Write};
use std::os::unix::fs::FileExt;
use std::path::{Path, PathBuf};
use std::sync::Mutex;
use tile::{Samples, Tile};

/// Version of the archive layout (the metadata and the tile payloads); readers refuse
/// others.
pub const ARCHIVE_VERSION: u32 = 1;
/// Quads a side of a tile at its own level: `(k - 1) 2^p` with the blocks' k = 33, p = 3
/// (SPEC section 8), so no block of LOD >= the tile's level straddles two tiles.
pub const TILE_QUADS: usize = 256;

/// What the archive says about the terrain (the PMTiles JSON metadata).
#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct Meta {
    /// Always "vkterrain terrain archive".
    pub kind: String,
    pub version: u32,
    /// True extent in samples (columns, rows).
    pub width: usize,
    pub height: usize,
    /// Quads a side of a tile ([`TILE_QUADS`]).
    pub tile_quads: usize,
    /// Top tile level `L`: one tile over `tile_quads * 2^L + 1` samples a side.
    pub top_level: u8,
    /// "unorm16" or "float32": how heights are stored (and go to the GPU).
    pub samples: String,
    pub spacing: [f32; 2],
    pub height_scale: f32,
    pub georef: Georef,
    /// Void samples the input had (filled before tiling).
    pub void_samples: usize,
    /// Where the heights came from, as `prepare` named it.
    pub source: String,
    /// Tiles stored (the archive's PMTiles entries).
    pub tiles: u64,
    /// Lowest and highest raw height of every sample: the colour ramp, sea level and
    /// default view of a streamed terrain, which holds only some of its samples, are
    /// then those of the same terrain in memory. Absent in archives written before it
    /// (their top tiles' range is used instead, and said so).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub raw_range: Option<[f32; 2]>,
    /// Whether the tiles say which of their vertices were voids (`prepare --voids
    /// hole`), so that they can be drawn as holes. Also cleared in an archive opened to
    /// draw its voids filled.
    #[serde(default, skip_serializing_if = "std::ops::Not::not")]
    pub void_mask: bool,
}

impl Meta {
    pub fn sample_format(&self) -> Result<Samples, String> {
        match self.samples.as_str() {
            "unorm16" => Ok(Samples::Unorm16),
            "float32" => Ok(Samples::Float32),
            s => Err(format!("unknown sample format '{s}'")),
        }
    }

    /// Tiles along each axis at `level` that touch the true extent.
    pub fn tiles_at(&self, level: u8) -> [u32; 2] {
        let span = self.tile_quads << level;
        [(self.width - 1).div_ceil(span) as u32, (self.height - 1).div_ceil(span) as u32]
    }

    /// Every stored tile, `(level, tx, tz)`, level by level, row by row.
    pub fn tiles(&self) -> impl Iterator<Item = (u8, u32, u32)> + '_ {
        (0..=self.top_level).flat_map(move |level| {
            let [nx, nz] = self.tiles_at(level);
            (0..nz).flat_map(move |tz| (0..nx).map(move |tx| (level, tx, tz)))
        })
    }

    /// `n` of the square the quadtree covers (`2^n + 1` samples a side).
    pub fn n(&self) -> u32 {
        self.tile_quads.trailing_zeros() + u32::from(self.top_level)
    }

    /// The smallest top level for a `width x height` terrain.
    pub fn top_level_for(width: usize, height: usize, tile_quads: usize) -> u8 {
        let mut level = 0u8;
        while (tile_quads << level) < width.max(height) - 1 {
            level += 1;
        }
        level
    }
}

/// Why an archive could not be read: always names the file, and the tile when one is
/// at fault.
pub fn bad(path: &Path, message: impl Into<String>) -> HeightfieldError {
    HeightfieldError::invalid(&bytes::shown(path), message)
}

/// An open archive: header, metadata and root directory read and checked; tiles read
/// on demand with positioned reads (any thread).
pub struct Archive {
    path: PathBuf,
    file: bytes::Bytes,
    len: u64,
    header: Header,
    root: Vec<Entry>,
    leaves: Mutex<HashMap<u64, std::sync::Arc<Vec<Entry>>>>,
    pub meta: Meta,
}

impl Archive {
    /// Is this file a PMTiles archive (by its first bytes)?
    pub fn sniff(path: &Path) -> bool {
        if bytes::is_url(path) {
            return true; // only archives are read from URLs
        }
        let mut magic = [0u8; 7];
        // A FIFO or device would block in open(): only regular files are archives.
        crate::input::regular_file(path).is_ok()
            && File::open(path).and_then(|f| f.read_exact_at(&mut magic, 0)).is_ok()
            && &magic == b"PMTiles"
    }

    /// Is `path` an archive: a URL, a `.pmtiles` name, or a file that starts like one?
    pub fn is_archive(path: &Path) -> bool {
        let pmtiles = path.extension().is_some_and(|e| e.eq_ignore_ascii_case("pmtiles"));
        bytes::is_url(path) || pmtiles || Archive::sniff(path)
    }

    /// The side of the grid of square roots (SPEC section 1) the archive needs in one
    /// image, read whole: more than the device's image side, and only streaming draws it.
    pub fn grid_side(&self) -> usize {
        let (n, roots) = crate::lod::heightfield::grid_cover(self.meta.width, self.meta.height);
        roots.map(|r| r * (1 << n) + 1).into_iter().max().unwrap_or(0)
    }

    pub fn open(path: &Path) -> Result<Archive, HeightfieldError> {
        // A FIFO would block in open(); the message already names the path.
        if !bytes::is_url(path) {
            if let Err(m) = crate::input::regular_file(path) {
                let shown = path.display().to_string();
                let problem = m.strip_prefix(&format!("{shown}: ")).unwrap_or(&m).to_string();
                return Err(HeightfieldError::invalid(&shown, problem));
            }
        }
        let (file, len) = bytes::Bytes::open(path).map_err(|e| bad(path, e))?;
        Archive::read(path, file, len)
    }

    /// An archive held in memory (written by [`ArchiveWriter::memory`]); `name` is what
    /// its messages call it (the file it was cut from).
    pub fn in_memory(name: &Path, archive: Vec<u8>) -> Result<Archive, HeightfieldError> {
        let len = archive.len() as u64;
        Archive::read(name, bytes::Bytes::Memory(archive), len)
    }

    /// Reads and checks the header, metadata and root directory of the archive in `file`.
    fn read(path: &Path, file: bytes::Bytes, len: u64) -> Result<Archive, HeightfieldError> {
        let read = |offset: u64, length: u64, what: &str| -> Result<Vec<u8>, HeightfieldError> {
            if offset.checked_add(length).is_none_or(|end| end > len) {
                return Err(bad(
                    path,
                    format!(
                        "{what} at bytes {offset}..{} lies past the end of the file ({len} bytes): truncated?",
                        offset.saturating_add(length)
                    ),
                ));
            }
            let mut buf = vec![0u8; length as usize];
            file.read_at(&mut buf, offset).map_err(|e| bad(path, format!("reading the {what}: {e}")))?;
            Ok(buf)
        };
        let head = read(0, (pmtiles::HEADER_LEN as u64).min(len), "header")?;
        let header = Header::decode(&head).map_err(|e| bad(path, e))?;
        header.check_sections().map_err(|e| bad(path, e))?;
        if header.internal_compression != pmtiles::COMPRESSION_GZIP
            || header.tile_compression != pmtiles::COMPRESSION_ZSTD
        {
            return Err(bad(
                path,
                "a PMTiles archive this build did not write (directories must be gzip and tiles zstd)",
            ));
        }
        let root = read(header.root_offset, header.root_len, "root directory")?;
        let root = pmtiles::decode_directory(&root).map_err(|e| bad(path, format!("root directory: {e}")))?;
        let meta = read(header.metadata_offset, header.metadata_len, "metadata")?;
        let meta = pmtiles::gunzip(&meta).map_err(|e| bad(path, format!("metadata does not decompress: {e}")))?;
        let meta: Meta = serde_json::from_slice(&meta).map_err(|e| {
            bad(path, format!("metadata is not a vkterrain archive's ({e}); was it written by `vkterrain prepare`?"))
        })?;
        if meta.kind != "vkterrain terrain archive" {
            return Err(bad(path, format!("metadata kind '{}' is not a vkterrain terrain archive", meta.kind)));
        }
        if meta.version != ARCHIVE_VERSION {
            return Err(bad(
                path,
                format!(
                    "archive version {} (this build reads version {ARCHIVE_VERSION}: prepare it again)",
                    meta.version
                ),
            ));
        }
        if let Some([lo, hi]) = meta.raw_range {
            if !(lo.is_finite() && hi.is_finite() && lo <= hi) {
                return Err(bad(path, format!("metadata height range {lo} to {hi} is not a range of heights")));
            }
        }
        meta.sample_format().map_err(|e| bad(path, e))?;
        if meta.tile_quads != TILE_QUADS || meta.width < 3 || meta.height < 3 || meta.top_level > 20 {
            return Err(bad(
                path,
                format!(
                    "metadata describes an impossible terrain ({} x {}, tiles of {})",
                    meta.width, meta.height, meta.tile_quads
                ),
            ));
        }
        if Meta::top_level_for(meta.width, meta.height, meta.tile_quads) != meta.top_level {
            return Err(bad(
                path,
                format!("top level {} does not fit a {} x {} terrain", meta.top_level, meta.width, meta.height),
            ));
        }
        // The header, the metadata and the quadtree agree on what is stored.
        let stored = meta.tiles().count() as u64;
        let counts = [header.addressed_tiles, header.tile_entries, header.tile_contents, meta.tiles];
        if counts.iter().any(|c| *c != stored) {
            return Err(bad(
                path,
                format!(
                    "the header counts {} addressed tiles, {} entries and {} contents, the metadata {}, but a {} x {} terrain stores {stored}",
                    counts[0], counts[1], counts[2], counts[3], meta.width, meta.height
                ),
            ));
        }
        if (header.min_zoom, header.max_zoom) != (0, meta.top_level) || header.tile_type != 0 {
            return Err(bad(
                path,
                format!(
                    "the header's zooms {}..={} (tile type {}) do not match the metadata's {} levels",
                    header.min_zoom,
                    header.max_zoom,
                    header.tile_type,
                    u32::from(meta.top_level) + 1
                ),
            ));
        }
        Ok(Archive { path: path.to_path_buf(), file, len, header, root, leaves: Mutex::new(HashMap::new()), meta })
    }

    /// Is this archive held in memory (a terrain file cut into tiles at load)?
    pub fn held_in_memory(&self) -> bool {
        matches!(self.file, bytes::Bytes::Memory(_))
    }

    pub fn path(&self) -> &Path {
        &self.path
    }

    /// Names tile `(level, tx, tz)` for messages: its PMTiles address and its samples.
    pub fn tile_name(&self, level: u8, tx: u32, tz: u32) -> String {
        let span = (self.meta.tile_quads as u64) << level;
        format!(
            "tile {}/{tx}/{tz} (level {level}, samples {}..={} x {}..={})",
            self.meta.top_level - level,
            tx as u64 * span,
            (tx as u64 + 1) * span,
            tz as u64 * span,
            (tz as u64 + 1) * span
        )
    }

    /// Every section the header names lies within the file (`check`; opening checks only
    /// that the header does not contradict itself, so that a truncated archive still
    /// streams what it holds).
    pub fn check_layout(&self) -> Result<(), HeightfieldError> {
        self.header.check_within(self.len).map_err(|e| bad(&self.path, e))
    }

    fn tile_error(&self, level: u8, tx: u32, tz: u32, message: impl std::fmt::Display) -> HeightfieldError {
        bad(&self.path, format!("{}: {message}", self.tile_name(level, tx, tz)))
    }

    /// Reads and checks tile `(level, tx, tz)`; `Ok(None)` where the archive stores no
    /// such tile (outside the true extent).
    pub fn read_tile(&self, level: u8, tx: u32, tz: u32) -> Result<Option<Tile>, HeightfieldError> {
        self.read_tile_counted(level, tx, tz).map(|(tile, _)| tile)
    }

    /// [`Archive::read_tile`] with the bytes read from the file for it (the compressed
    /// payload; directories are read once and cached).
    pub fn read_tile_counted(&self, level: u8, tx: u32, tz: u32) -> Result<(Option<Tile>, u64), HeightfieldError> {
        if level > self.meta.top_level {
            return Ok((None, 0));
        }
        let [nx, nz] = self.meta.tiles_at(level);
        if tx >= nx || tz >= nz {
            return Ok((None, 0));
        }
        let id = pmtiles::tile_id(self.meta.top_level - level, tx, tz);
        let err = |m: String| self.tile_error(level, tx, tz, m);
        let mut entry = pmtiles::find(&self.root, id);
        if let Some(leaf) = entry.filter(|e| e.run_length == 0) {
            let dir = self.leaf(leaf).map_err(err)?;
            entry = pmtiles::find(&dir, id).filter(|e| e.run_length > 0);
        }
        let Some(e) = entry else {
            return Err(err("missing from the archive's directory".into()));
        };
        if e.offset.checked_add(u64::from(e.length)).is_none_or(|end| end > self.header.data_len) {
            return Err(err(format!(
                "its entry (bytes {}.. of tile data, {} long) lies outside the tile data section ({} bytes): the archive is corrupt",
                e.offset, e.length, self.header.data_len
            )));
        }
        let start = self.header.data_offset.checked_add(e.offset);
        let end = start.and_then(|s| s.checked_add(u64::from(e.length)));
        if end.is_none_or(|end| end > self.len) {
            return Err(err(format!(
                "its data lies past the end of the file ({} bytes): the archive is truncated",
                self.len
            )));
        }
        let mut buf = vec![0u8; e.length as usize];
        self.file.read_at(&mut buf, start.expect("checked")).map_err(|e| err(format!("read failed: {e}")))?;
        let samples = self.meta.sample_format().expect("checked at open");
        let side = self.meta.tile_quads + 3;
        let limit = tile::payload_len(samples, side, self.deviations(level), true);
        let payload = pmtiles::unzstd(&buf, limit)
            .map_err(|e| err(format!("does not decompress ({e}): the archive is corrupt")))?;
        let mut tile = tile::decode(&payload, samples, level, tx, tz, side, self.deviations(level)).map_err(err)?;
        if !self.meta.void_mask {
            // Drawn with its voids filled: the mask, if any, is not wanted.
            tile.voids = None;
        }
        Ok((Some(tile), u64::from(e.length)))
    }

    /// Values of `D` a tile of `level` holds: `T^2` of its own level (none at level 0),
    /// and at the top every coarser level's as well.
    pub fn deviations(&self, level: u8) -> usize {
        let t = self.meta.tile_quads;
        let own = if level == 0 { 0 } else { t * t };
        if level < self.meta.top_level {
            return own;
        }
        let n = self.meta.n();
        own + (u32::from(level) + 1..=n).map(|l| ((t << level >> l).max(1)).pow(2)).sum::<usize>()
    }

    fn leaf(&self, pointer: Entry) -> Result<std::sync::Arc<Vec<Entry>>, String> {
        if let Some(dir) = self.leaves.lock().expect("leaf cache").get(&pointer.offset) {
            return Ok(dir.clone());
        }
        if pointer.offset.checked_add(u64::from(pointer.length)).is_none_or(|end| end > self.header.leaf_len) {
            return Err(
                "its leaf directory's entry lies outside the leaf directories' section: the archive is corrupt".into(),
            );
        }
        let start = self.header.leaf_offset.checked_add(pointer.offset);
        let end = start.and_then(|s| s.checked_add(u64::from(pointer.length)));
        if end.is_none_or(|end| end > self.len) {
            return Err("its leaf directory lies past the end of the file: the archive is truncated".into());
        }
        let mut buf = vec![0u8; pointer.length as usize];
        self.file.read_at(&mut buf, start.expect("checked")).map_err(|e| format!("reading its leaf directory: {e}"))?;
        let dir = std::sync::Arc::new(pmtiles::decode_directory(&buf).map_err(|e| format!("its leaf directory: {e}"))?);
        self.leaves.lock().expect("leaf cache").insert(pointer.offset, dir.clone());
        Ok(dir)
    }

    /// Every `2^level`-th sample of the terrain along both axes as one heightfield
    /// ([`level_heightfield`]), every tile of the level read and checked.
    pub fn level_heightfield(&self, level: u8) -> Result<Heightfield, HeightfieldError> {
        let m = &self.meta;
        let format = match m.sample_format().expect("checked at open") {
            Samples::Unorm16 => HeightFormat::Unorm16,
            Samples::Float32 => HeightFormat::Float32,
        };
        let terrain = LevelTerrain {
            name: &bytes::shown(&self.path),
            extent: [m.width, m.height],
            tile_quads: m.tile_quads,
            format,
            spacing: m.spacing,
            height_scale: m.height_scale,
        };
        level_heightfield(&terrain, level, |tx, tz| {
            self.read_tile(level, tx, tz)?.ok_or_else(|| self.tile_error(level, tx, tz, "missing"))
        })
    }

    /// The whole terrain at full resolution as one heightfield (level-0 tiles), for
    /// terrains that fit in one GPU image; every tile is read and its checksum verified.
    pub fn heightfield(&self) -> Result<Heightfield, HeightfieldError> {
        let m = &self.meta;
        if m.width > crate::lod::heightfield::MAX_SIDE || m.height > crate::lod::heightfield::MAX_SIDE {
            return Err(bad(
                &self.path,
                format!(
                    "a {} x {} terrain does not fit in memory as one image (at most {} samples a side); \
                     `view`, `render`, `bench --stream` and `stream` draw it streamed",
                    m.width,
                    m.height,
                    crate::lod::heightfield::MAX_SIDE
                ),
            ));
        }
        let mut hf = self.level_heightfield(0)?;
        // The coarser tiles are not needed here, but a damaged one is better found now.
        for (level, tx, tz) in m.tiles().filter(|&(level, _, _)| level > 0) {
            self.read_tile(level, tx, tz)?.ok_or_else(|| self.tile_error(level, tx, tz, "missing"))?;
        }
        hf.georef = m.georef.clone();
        hf.georef.notes.insert(0, format!("a prepared archive of {} tiles, from {}", m.tiles, m.source));
        hf.void_samples = m.void_samples;
        Ok(hf)
    }
}

/// What [`level_heightfield`] needs of a terrain.
pub struct LevelTerrain<'a> {
    /// The file, for errors.
    pub name: &'a str,
    /// True extent in samples.
    pub extent: [usize; 2],
    pub tile_quads: usize,
    pub format: HeightFormat,
    pub spacing: [f32; 2],
    pub height_scale: f32,
}

/// Every `2^level`-th sample of `terrain` along both axes as one heightfield: the
/// vertices of the level's tiles as `read(tx, tz)` gives them, `((width - 1) >> level) +
/// 1` by `((height - 1) >> level) + 1`, spacing `2^level` times the terrain's. Level 0 is
/// the whole terrain ([`Archive::heightfield`]); a coarser level is what streamed frames
/// make their lighting map from.
pub fn level_heightfield<E: From<HeightfieldError>>(
    terrain: &LevelTerrain,
    level: u8,
    mut read: impl FnMut(u32, u32) -> Result<Tile, E>,
) -> Result<Heightfield, E> {
    let [w, h] = terrain.extent.map(|e| ((e - 1) >> level) + 1);
    let t = terrain.tile_quads;
    let mut samples = vec![0.0f32; w * h];
    for tz in 0..(h - 1).div_ceil(t) as u32 {
        for tx in 0..(w - 1).div_ceil(t) as u32 {
            let tile = read(tx, tz)?;
            let x0 = tx as usize * t;
            for j in 0..=t {
                let z = tz as usize * t + j;
                if z >= h {
                    break;
                }
                let count = (t + 1).min(w - x0);
                let row = &tile.heights[(j + 1) * tile.side + 1..][..count];
                samples[z * w + x0..][..count].copy_from_slice(row);
            }
        }
    }
    let stride = (1u32 << level) as f32;
    let spacing = Spacing::from([terrain.spacing[0] * stride, terrain.spacing[1] * stride]);
    Ok(Heightfield::embed(terrain.name, w, h, &samples, terrain.format, spacing, terrain.height_scale)?)
}

/// Removes `.NAME.partial-PID` files beside `out` whose process is gone (a run killed by
/// SIGKILL or a crash cannot remove its own). A live PID's file is another run's: left.
fn remove_stale_partials(out: &Path, name: &str) {
    let dir = match out.parent() {
        Some(d) if !d.as_os_str().is_empty() => d,
        _ => Path::new("."),
    };
    // `PID` or `PID-ordered` (the second file of the ordering pass).
    for stale in crate::input::left_by_dead_runs(dir, &format!(".{name}.partial-")) {
        let _ = std::fs::remove_file(stale);
    }
}

/// Writes an archive: tiles streamed into the data section as they are made (any
/// order), directories and metadata at the end, the header last. Into a file, which
/// appears under its name only when [`ArchiveWriter::finish`] succeeds (until then it is
/// a hidden temporary beside it, removed on drop: an error or an interrupted run leaves
/// nothing); or into memory ([`ArchiveWriter::memory`]), for a terrain file cut into
/// tiles at load, with nothing written.
pub struct ArchiveWriter {
    sink: Sink,
    entries: Vec<Entry>,
    data_len: u64,
}

/// Where an [`ArchiveWriter`]'s bytes go.
enum Sink {
    /// A hidden temporary beside `out`, renamed to it when finished.
    File {
        out: PathBuf,
        tmp: PathBuf,
        file: Option<std::io::BufWriter<File>>,
    },
    Memory(std::io::Cursor<Vec<u8>>),
}

impl ArchiveWriter {
    pub fn create(out: &Path) -> std::io::Result<ArchiveWriter> {
        let name = out.file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_else(|| "archive".into());
        remove_stale_partials(out, &name);
        let tmp = out.with_file_name(format!(".{name}.partial-{}", std::process::id()));
        let mut file = std::io::BufWriter::with_capacity(1 << 20, File::create(&tmp)?);
        // The header and root directory go in the first 16 KiB once the tiles are known.
        file.write_all(&vec![0u8; pmtiles::ROOT_LIMIT])?;
        let sink = Sink::File { out: out.to_path_buf(), tmp, file: Some(file) };
        Ok(ArchiveWriter { sink, entries: Vec::new(), data_len: 0 })
    }

    /// A writer whose archive stays in memory ([`ArchiveWriter::finish_in_memory`]).
    pub fn memory() -> ArchiveWriter {
        let mut cursor = std::io::Cursor::new(vec![0u8; pmtiles::ROOT_LIMIT]);
        cursor.set_position(pmtiles::ROOT_LIMIT as u64);
        ArchiveWriter { sink: Sink::Memory(cursor), entries: Vec::new(), data_len: 0 }
    }

    fn write_all(&mut self, bytes: &[u8]) -> std::io::Result<()> {
        match &mut self.sink {
            Sink::File { file, .. } => file.as_mut().expect("not finished").write_all(bytes),
            Sink::Memory(cursor) => cursor.write_all(bytes),
        }
    }

    /// Appends tile `(level, tx, tz)` (its payload compressed, [`pmtiles::zstd`]); `top` is
    /// the archive's top level. Returns the compressed size.
    pub fn add(&mut self, top: u8, level: u8, tx: u32, tz: u32, compressed: &[u8]) -> std::io::Result<usize> {
        self.write_all(compressed)?;
        self.entries.push(Entry {
            tile_id: pmtiles::tile_id(top - level, tx, tz),
            offset: self.data_len,
            length: compressed.len() as u32,
            run_length: 1,
        });
        self.data_len += compressed.len() as u64;
        Ok(compressed.len())
    }

    /// Rewrites the data section in tile-id order (PMTiles "clustered"): the workers
    /// append tiles as they finish, in an order that changes from run to run; ordered,
    /// the same input makes the same bytes, and a reader over HTTP reads neighbours
    /// together. One sequential copy, a tile at a time.
    fn order_tiles(&mut self) -> std::io::Result<()> {
        self.entries.sort_by_key(|e| e.tile_id);
        if self.entries.windows(2).all(|w| w[0].offset < w[1].offset) {
            return Ok(());
        }
        let (tmp, file) = match &mut self.sink {
            Sink::File { tmp, file, .. } => (tmp, file),
            Sink::Memory(cursor) => {
                let old = std::mem::take(cursor.get_mut());
                let mut ordered = Vec::with_capacity(old.len());
                ordered.extend_from_slice(&old[..pmtiles::ROOT_LIMIT]);
                for e in &mut self.entries {
                    let start = pmtiles::ROOT_LIMIT + e.offset as usize;
                    e.offset = (ordered.len() - pmtiles::ROOT_LIMIT) as u64;
                    ordered.extend_from_slice(&old[start..start + e.length as usize]);
                }
                *cursor = std::io::Cursor::new(ordered);
                cursor.seek(SeekFrom::End(0))?;
                return Ok(());
            }
        };
        // Flushed and closed (it was opened write-only), then read back.
        drop(file.take().expect("not finished").into_inner().map_err(|e| e.into_error())?);
        let old = File::open(&*tmp)?;
        let ordered = PathBuf::from(format!("{}-ordered", tmp.display()));
        // Removed on every path out of here but success (then it becomes `tmp`).
        struct Guard(Option<PathBuf>);
        impl Drop for Guard {
            fn drop(&mut self) {
                if let Some(p) = self.0.take() {
                    let _ = std::fs::remove_file(p);
                }
            }
        }
        let mut guard = Guard(Some(ordered.clone()));
        let mut out = std::io::BufWriter::with_capacity(1 << 20, File::create(&ordered)?);
        out.write_all(&vec![0u8; pmtiles::ROOT_LIMIT])?;
        let mut buf = Vec::new();
        let mut offset = 0u64;
        for e in &mut self.entries {
            buf.resize(e.length as usize, 0);
            old.read_exact_at(&mut buf, pmtiles::ROOT_LIMIT as u64 + e.offset)?;
            out.write_all(&buf)?;
            e.offset = offset;
            offset += u64::from(e.length);
        }
        drop(old);
        std::fs::remove_file(&*tmp)?;
        *tmp = guard.0.take().expect("set above");
        *file = Some(out);
        Ok(())
    }

    /// Orders the tiles, writes directories, metadata and header, syncs, and moves the
    /// file into place. Returns the archive's size.
    pub fn finish(mut self, meta: &mut Meta) -> std::io::Result<u64> {
        let len = self.close(meta)?;
        if let Sink::File { out, tmp, file } = &mut self.sink {
            let file = file.take().expect("not finished").into_inner().map_err(|e| e.into_error())?;
            file.sync_all()?;
            std::fs::rename(&*tmp, &*out)?;
        }
        Ok(len)
    }

    /// [`ArchiveWriter::finish`] for a writer made by [`ArchiveWriter::memory`]: the
    /// archive's bytes.
    pub fn finish_in_memory(mut self, meta: &mut Meta) -> std::io::Result<Vec<u8>> {
        self.close(meta)?;
        match &mut self.sink {
            Sink::Memory(cursor) => Ok(std::mem::take(cursor.get_mut())),
            Sink::File { .. } => Err(std::io::Error::other("an archive written to a file is not held in memory")),
        }
    }

    /// Everything after the tiles, and the header and root in front; the archive's size.
    fn close(&mut self, meta: &mut Meta) -> std::io::Result<u64> {
        self.order_tiles()?;
        meta.tiles = self.entries.len() as u64;
        let (root, leaves) = pmtiles::directories(&self.entries);
        let json = pmtiles::gzip(&serde_json::to_vec(meta).expect("metadata serialises"), 6);
        let data_offset = pmtiles::ROOT_LIMIT as u64;
        // The metadata goes in the first 16 KiB with the root when it fits, so that a
        // truncated archive still says what it is and which tile is cut off.
        let root_end = (pmtiles::HEADER_LEN + root.len()) as u64;
        let front = root_end + json.len() as u64 <= data_offset;
        let metadata_offset = if front { root_end } else { data_offset + self.data_len };
        let leaf_offset = if front { data_offset + self.data_len } else { metadata_offset + json.len() as u64 };
        let header = Header {
            root_offset: pmtiles::HEADER_LEN as u64,
            root_len: root.len() as u64,
            metadata_offset,
            metadata_len: json.len() as u64,
            leaf_offset,
            leaf_len: leaves.len() as u64,
            data_offset,
            data_len: self.data_len,
            addressed_tiles: self.entries.len() as u64,
            tile_entries: self.entries.len() as u64,
            tile_contents: self.entries.len() as u64,
            clustered: true,
            internal_compression: pmtiles::COMPRESSION_GZIP,
            tile_compression: pmtiles::COMPRESSION_ZSTD,
            tile_type: 0,
            min_zoom: 0,
            max_zoom: meta.top_level,
        };
        if !front {
            self.write_all(&json)?;
        }
        self.write_all(&leaves)?;
        let mut front_part = header.encode().to_vec();
        front_part.extend_from_slice(&root);
        if front {
            front_part.extend_from_slice(&json);
        }
        match &mut self.sink {
            Sink::File { file, .. } => {
                let file = file.as_mut().expect("not finished");
                file.flush()?;
                let inner = file.get_mut();
                inner.seek(SeekFrom::Start(0))?;
                inner.write_all(&front_part)?;
            }
            Sink::Memory(cursor) => cursor.get_mut()[..front_part.len()].copy_from_slice(&front_part),
        }
        Ok(data_offset + self.data_len + if front { 0 } else { json.len() as u64 } + leaves.len() as u64)
    }
}

impl Drop for ArchiveWriter {
    fn drop(&mut self) {
        if let Sink::File { tmp, file, .. } = &mut self.sink {
            if file.take().is_some() || tmp.exists() {
                let _ = std::fs::remove_file(&*tmp);
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Archives written before `raw_range` existed still open (without it), and one
    /// without a range writes none.
    #[test]
    fn the_height_range_is_optional_in_the_metadata() {
        let meta = Meta {
            kind: "vkterrain terrain archive".into(),
            version: ARCHIVE_VERSION,
            width: 257,
            height: 257,
            tile_quads: TILE_QUADS,
            top_level: 0,
            samples: "unorm16".into(),
            spacing: [1.0, 1.0],
            height_scale: 0.1,
            georef: Georef::default(),
            void_samples: 0,
            source: "test".into(),
            tiles: 1,
            raw_range: Some([-3.0, 7.5]),
            void_mask: false,
        };
        let json = serde_json::to_value(&meta).unwrap();
        assert_eq!(json["raw_range"], serde_json::json!([-3.0, 7.5]));
        assert_eq!(serde_json::from_value::<Meta>(json.clone()).unwrap(), meta);
        let mut old = json;
        old.as_object_mut().unwrap().remove("raw_range");
        let read: Meta = serde_json::from_value(old).unwrap();
        assert_eq!(read.raw_range, None);
        assert!(serde_json::to_value(&read).unwrap().get("raw_range").is_none());
    }
}
