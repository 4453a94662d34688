//! Streaming a terrain of any size from a tile archive (SPEC section 8, issue 27): the
//! host side, plain Rust without Vulkan.
//!
//! - [`io`]: the IO thread (the third thread), reading and decoding the tiles the
//!   traversal asks for, newest request first;
//! - [`cache`]: the host cache: a fixed byte budget, ancestor-closed, least recently used
//!   among the tiles the current frame does not need; each tile's per-block summaries
//!   (vertex range, the exact deviation `D`) computed once on arrival;
//! - [`traverse`]: the traversal over resident tiles, in f64 world coordinates relative
//!   to the camera's sample, with the bound kept honest: a block that should split but
//!   whose finer tile is not resident is drawn as it is, requested and counted.
//!
//! - [`morph`]: the drawn blocks' geomorph, paid for inside the bound from the tiles'
//!   summaries;
//! - [`draw`]: a selection's blocks stitched as the vertex shader draws them, read from
//!   the held tiles.

pub mod cache;
pub mod draw;
pub mod errors;
pub mod io;
pub mod morph;
pub mod streamer;
pub mod traverse;

use crate::input::archive::Meta;

/// A tile of the archive's quadtree: level `level` (0 finest), column `tx`, row `tz`.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub struct TileKey {
    pub level: u8,
    pub tx: u32,
    pub tz: u32,
}

impl TileKey {
    pub const fn new(level: u8, tx: u32, tz: u32) -> Self {
        TileKey { level, tx, tz }
    }

    /// The tile one level coarser that covers this one; `None` at the top.
    pub fn parent(self, top: u8) -> Option<TileKey> {
        (self.level < top).then(|| TileKey::new(self.level + 1, self.tx / 2, self.tz / 2))
    }
}

/// What the traversal needs of an archive's frame: size, quadtree, world scale, and
/// where sample (0, 0) lies in the world (f64: far from the origin, f32 would lose the
/// samples' spacing).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Grid {
    /// True extent in samples.
    pub width: usize,
    pub height: usize,
    /// Quads a side of a tile at its own level (`T`).
    pub tile_quads: usize,
    /// Top tile level.
    pub top: u8,
    /// World units between samples (x, z) and per raw height unit.
    pub spacing: [f64; 2],
    pub height_scale: f64,
    /// World position of sample (0, 0) in x and z.
    pub origin: [f64; 2],
    /// Bytes a height takes decoded: 2 (16-bit archives) or 4 (float).
    pub height_bytes: usize,
    /// Quads a side of a block (`k - 1`, `--block`): a tile of its own level holds
    /// `tile_quads / block_quads` blocks a side.
    pub block_quads: usize,
    /// Voids are drawn as holes (`--voids hole`): tiles say which vertices are voids.
    pub holes: bool,
}

/// Quads a side of a block unless `--block` says otherwise (blocks of k = 33, the paper's).
pub const DEFAULT_BLOCK_QUADS: usize = 32;

/// Squares a block side whose deviation is kept apart
/// ([`cache::BlockSummary::squares`]).
pub const SUB: usize = 8;

impl Grid {
    pub fn from_meta(m: &Meta) -> Self {
        Grid {
            width: m.width,
            height: m.height,
            tile_quads: m.tile_quads,
            top: m.top_level,
            spacing: [f64::from(m.spacing[0]), f64::from(m.spacing[1])],
            height_scale: f64::from(m.height_scale),
            origin: [0.0, 0.0],
            height_bytes: if m.samples == "float32" { 4 } else { 2 },
            block_quads: DEFAULT_BLOCK_QUADS,
            holes: m.void_mask,
        }
    }

    /// Bytes of one texel of the heightfield atlas: a height, and with holes beside it
    /// whether it is a void (a second channel of the same format).
    pub fn atlas_texel_bytes(&self) -> usize {
        self.height_bytes * if self.holes { 2 } else { 1 }
    }

    /// The same grid drawn with blocks of `k` vertices a side (`--block`). A block is
    /// summarised as [`SUB`]` x `[`SUB`] squares, so it has at least that
    /// many quads a side; and the paper's errors of a block one LOD coarser than a tile
    /// come from that tile's own vertices, so a tile holds at least two blocks a side.
    pub fn with_block(self, k: u32) -> Result<Self, String> {
        let most = self.tile_quads / 2;
        let quads = (k as usize).saturating_sub(1);
        if !quads.is_power_of_two() || quads < SUB || quads > most {
            let sides: Vec<String> =
                (0..).map(|i| (SUB << i) + 1).take_while(|&s| s <= most + 1).map(|s| s.to_string()).collect();
            return Err(format!(
                "--block {k}: a terrain drawn from tiles of {} quads takes blocks of {} vertices a side",
                self.tile_quads,
                sides.join(", ")
            ));
        }
        Ok(Grid { block_quads: quads, ..self })
    }

    /// World size of the true extent along x and z (from sample 0 to the last).
    pub fn world_extent(&self) -> [f64; 2] {
        [(self.width - 1) as f64 * self.spacing[0], (self.height - 1) as f64 * self.spacing[1]]
    }

    /// The same grid with sample (0, 0) at world `(x, z)`.
    pub fn at(self, origin: [f64; 2]) -> Self {
        Grid { origin, ..self }
    }

    /// Samples a side of a tile of `level`.
    pub fn tile_span(&self, level: u8) -> usize {
        self.tile_quads << level
    }

    /// Tiles along x and z at `level` that touch the true extent (those stored).
    pub fn tiles_at(&self, level: u8) -> [u32; 2] {
        let span = self.tile_span(level);
        [(self.width - 1).div_ceil(span) as u32, (self.height - 1).div_ceil(span) as u32]
    }

    /// Is this tile stored in the archive (inside the quadtree and the true extent)?
    pub fn stores(&self, key: TileKey) -> bool {
        let [nx, nz] = self.tiles_at(key.level.min(self.top));
        key.level <= self.top && key.tx < nx && key.tz < nz
    }

    /// World x and z of sample `(x, z)` (f64).
    pub fn world_xz(&self, x: f64, z: f64) -> [f64; 2] {
        [self.origin[0] + x * self.spacing[0], self.origin[1] + z * self.spacing[1]]
    }

    /// Sample coordinates of world x, z (f64, fractional).
    pub fn sample_of(&self, wx: f64, wz: f64) -> [f64; 2] {
        [(wx - self.origin[0]) / self.spacing[0], (wz - self.origin[1]) / self.spacing[1]]
    }
}
