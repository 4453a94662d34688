//! The host cache of decoded tiles (SPEC section 8, "Residency" and "Budgets"): a fixed
//! byte budget, residency closed under ancestors (a tile is held only with its parent),
//! eviction of the least recently used tile that no held tile depends on and that the
//! current frame did not use. Each tile's per-block summaries are computed once, when it
//! arrives, so a frame's traversal reads three numbers a block.

use super::{Grid, TileKey};
use crate::input::archive::tile::Tile;
use crate::lod::block::BlockLayout;
use crate::lod::heightfield::RawSamples;
use foldhash::{HashMap, HashMapExt};
use std::sync::Arc;

/// What the bound needs of one block of LOD `j`, in raw height units: the range of its
/// LOD-`j` vertices, `D_j`, the largest deviation of the full-resolution samples from its
/// surface, and the heights both can take: every sample under the block and every point
/// of its surface lie in `[min, max]`, within `[lo - d, hi + d]` (each group's samples lie
/// within its own `D` of its quad, which lies between the quad's corners).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct BlockSummary {
    pub lo: f32,
    pub hi: f32,
    pub d: f32,
    pub min: f32,
    pub max: f32,
    /// The same of each of the block's `SUB x SUB` squares (row-major, `block_quads /
    /// SUB` groups a side): the traversal bounds each from its own box, as the in-memory
    /// error images bound each group at its own distance ([`crate::stream::traverse`]).
    pub squares: [Square; SUB * SUB],
    /// The largest `D_j` of the row of groups along each edge (north, east, south, west),
    /// over each square it crosses: a stitched strip's samples deviate from the block's
    /// own surface by no more ([`crate::stream::traverse`]).
    pub edge_d: [[f32; SUB]; 4],
    /// A void drawn as a hole lies in the block's area, as its tile's mask says (a
    /// coarser tile's flags each cover their vertex's neighbourhood): the traversal draws
    /// it at LOD 0, whose tile holds the voids exactly.
    pub voids: bool,
}

/// A square of a block: the largest `D_j` of its groups and the heights its samples and
/// surface lie between, raw units.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Square {
    pub d: f32,
    pub min: f32,
    pub max: f32,
}

pub use super::SUB;

/// The LOD of the blocks the archive's roots are: one block over the top tile's square.
pub fn root_lod(grid: &Grid) -> u32 {
    (grid.tile_span(grid.top) / grid.block_quads).trailing_zeros()
}

/// The tile a block of LOD `lod` at block coordinates `(bx, bz)` is drawn from: the tile
/// of level `lod` that covers it, or the top tile for blocks coarser than the top level.
pub fn serving_tile(grid: &Grid, lod: u32, bx: u32, bz: u32) -> TileKey {
    let level = lod.min(u32::from(grid.top)) as u8;
    let per_tile = (grid.tile_span(level) / (grid.block_quads << lod)).max(1) as u32;
    TileKey::new(level, bx / per_tile, bz / per_tile)
}

/// A tile's heights as held: 16-bit when every one is an integer in 0..=65535 (a 16-bit
/// source, the common case), which halves a tile of level 0; exact either way.
#[derive(Debug)]
pub enum Heights {
    Unorm16(Vec<u16>),
    Float32(Vec<f32>),
}

impl Heights {
    fn compact(heights: Vec<f32>) -> Heights {
        let fits = heights.iter().all(|&h| h.fract() == 0.0 && (0.0..=65535.0).contains(&h));
        if fits {
            Heights::Unorm16(heights.iter().map(|&h| h as u16).collect())
        } else {
            Heights::Float32(heights)
        }
    }

    pub fn get(&self, i: usize) -> f32 {
        match self {
            Heights::Unorm16(v) => f32::from(v[i]),
            Heights::Float32(v) => v[i],
        }
    }

    pub fn bytes(&self) -> usize {
        match self {
            Heights::Unorm16(v) => v.len() * 2,
            Heights::Float32(v) => v.len() * 4,
        }
    }
}

/// A decoded tile and its blocks' summaries, per LOD it serves (its own level; the top
/// tile also every coarser LOD up to the root).
#[derive(Debug)]
pub struct TileData {
    pub key: TileKey,
    /// Samples a side, the one-sample border included (vertex `(i, j)` of the tile's
    /// square is sample `(i + 1, j + 1)`).
    pub side: usize,
    pub heights: Heights,
    /// `D` of the tile's groups, as [`Tile::deviation`].
    pub deviation: Vec<f32>,
    /// Which samples (as `heights`) are voids drawn as holes, as [`Tile::voids`].
    pub voids: Option<Vec<bool>>,
    /// `blocks[j - level]`: row-major, `(T / block_quads >> (j - level))^2`.
    blocks: Vec<Vec<BlockSummary>>,
    /// Bytes held (heights, deviations, summaries).
    pub bytes: usize,
}

impl TileData {
    pub fn new(grid: &Grid, tile: Tile) -> Result<Self, String> {
        let key = TileKey::new(tile.level, tile.tx, tile.tz);
        let t = grid.tile_quads;
        if tile.side != t + 3 {
            return Err(format!("tile {key:?} is {} samples a side, expected {}", tile.side, t + 3));
        }
        let level = u32::from(key.level);
        let last = if key.level == grid.top { root_lod(grid) } else { level };
        let vertex = |i: usize, j: usize| tile.heights[(j + 1) * tile.side + i + 1];
        let quads = grid.block_quads;
        // Where D_j of this tile starts in `tile.deviation` and its side in groups.
        let mut offset = 0usize;
        let mut blocks = Vec::new();
        for j in level..=last {
            let groups = t >> (j - level);
            let per_side = groups / quads;
            let stride = 1usize << (j - level);
            let has_d = j > 0;
            if has_d && offset + groups * groups > tile.deviation.len() {
                return Err(format!("tile {key:?} holds {} deviations, too few for LOD {j}", tile.deviation.len()));
            }
            let mut summaries = Vec::with_capacity(per_side * per_side);
            for bz in 0..per_side {
                for bx in 0..per_side {
                    let q = quads / SUB;
                    let mut squares = [Square { d: 0.0, min: f32::INFINITY, max: f32::NEG_INFINITY }; SUB * SUB];
                    let mut edge_d = [[0.0f32; SUB]; 4];
                    let (mut lo, mut hi) = (f32::INFINITY, f32::NEG_INFINITY);
                    for gz in 0..quads {
                        for gx in 0..quads {
                            let corner = |u: usize, v: usize| {
                                vertex((bx * quads + gx + u) * stride, (bz * quads + gz + v) * stride)
                            };
                            let c = [corner(0, 0), corner(1, 0), corner(0, 1), corner(1, 1)];
                            let (cmin, cmax) = (
                                c.into_iter().fold(f32::INFINITY, f32::min),
                                c.into_iter().fold(f32::NEG_INFINITY, f32::max),
                            );
                            let g = if has_d {
                                tile.deviation[offset + (bz * quads + gz) * groups + bx * quads + gx]
                            } else {
                                0.0
                            };
                            let s = &mut squares[gz / q * SUB + gx / q];
                            s.d = s.d.max(g);
                            (s.min, s.max) = (s.min.min(cmin - g), s.max.max(cmax + g));
                            (lo, hi) = (lo.min(cmin), hi.max(cmax));
                            let last = quads - 1;
                            for (e, on) in [gz == 0, gx == last, gz == last, gx == 0].into_iter().enumerate() {
                                if on {
                                    let k = if e % 2 == 0 { gx / q } else { gz / q };
                                    edge_d[e][k] = edge_d[e][k].max(g);
                                }
                            }
                        }
                    }
                    let fold =
                        |f: fn(&Square) -> f32, m: fn(f32, f32) -> f32, from: f32| squares.iter().map(f).fold(from, m);
                    let d = fold(|s| s.d, f32::max, 0.0);
                    let (min, max) =
                        (fold(|s| s.min, f32::min, f32::INFINITY), fold(|s| s.max, f32::max, f32::NEG_INFINITY));
                    let span = quads * stride;
                    let voids = tile.voids.as_ref().is_some_and(|v| {
                        (bz * span..=(bz + 1) * span)
                            .any(|j| (bx * span..=(bx + 1) * span).any(|i| v[(j + 1) * tile.side + i + 1]))
                    });
                    summaries.push(BlockSummary { lo, hi, d, min, max, squares, edge_d, voids });
                }
            }
            if has_d {
                offset += groups * groups;
            }
            blocks.push(summaries);
        }
        let (side, heights, deviation, voids) = (tile.side, Heights::compact(tile.heights), tile.deviation, tile.voids);
        let bytes = heights.bytes()
            + deviation.len() * 4
            + voids.as_ref().map_or(0, Vec::len)
            + blocks.iter().map(|b| b.len() * std::mem::size_of::<BlockSummary>()).sum::<usize>()
            + std::mem::size_of::<Self>();
        Ok(TileData { key, side, heights, deviation, voids, blocks, bytes })
    }

    /// Raw height of vertex `(i, j)` of the tile's square (its own level's spacing).
    pub fn vertex(&self, i: usize, j: usize) -> f32 {
        self.heights.get((j + 1) * self.side + i + 1)
    }

    /// Whether vertex `(i, j)` of the tile's square is a void drawn as a hole.
    pub fn void(&self, i: usize, j: usize) -> bool {
        self.voids.as_ref().is_some_and(|v| v[(j + 1) * self.side + i + 1])
    }

    /// `D` of group `(gx, gz)` (terrain group coordinates) of LOD `lod`, which this tile
    /// serves (`D_0` is 0): the layout [`TileData::new`] reads.
    pub fn group_d(&self, grid: &Grid, lod: u32, gx: usize, gz: usize) -> f32 {
        if lod == 0 {
            return 0.0;
        }
        let (t, level) = (grid.tile_quads, u32::from(self.key.level));
        let offset: usize = (level.max(1)..lod).map(|j| (t >> (j - level)).pow(2)).sum();
        let groups = t >> (lod - level);
        let (lx, lz) = (gx - self.key.tx as usize * groups, gz - self.key.tz as usize * groups);
        self.deviation[offset + lz * groups + lx]
    }

    /// The summary of block `(bx, bz)` (terrain block coordinates) of LOD `lod`, which
    /// this tile serves.
    pub fn block(&self, grid: &Grid, lod: u32, bx: u32, bz: u32) -> BlockSummary {
        let j = (lod - u32::from(self.key.level)) as usize;
        let per_side = (grid.tile_quads >> j) / grid.block_quads;
        let (lx, lz) = (bx as usize - self.key.tx as usize * per_side, bz as usize - self.key.tz as usize * per_side);
        self.blocks[j][lz * per_side + lx]
    }
}

/// About what a tile of `level` takes decoded ([`TileData::bytes`], the top tile's
/// coarser deviations left out): to ask the IO thread only for what can be held.
pub fn tile_bytes_estimate(grid: &Grid, level: u8) -> usize {
    let t = grid.tile_quads;
    let own_d = if level > 0 { t * t } else { 0 };
    let summaries = (t / grid.block_quads).pow(2) * std::mem::size_of::<BlockSummary>();
    let voids = if grid.holes { (t + 3) * (t + 3) } else { 0 };
    (t + 3) * (t + 3) * grid.height_bytes + voids + own_d * 4 + summaries + 4096
}

/// Why a tile was not taken into the cache.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Refused {
    /// Its parent is not held (residency is ancestor-closed).
    NoParent,
    /// Every held tile is needed (used this frame, or a parent): nothing can go.
    Full,
}

#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, serde::Serialize)]
pub struct CacheStats {
    pub inserted: u64,
    pub evicted: u64,
    pub refused_full: u64,
    pub refused_orphan: u64,
    pub peak_bytes: usize,
}

struct Held {
    data: Arc<TileData>,
    /// Last frame that drew from it (protected during that frame).
    last_used: u64,
    /// Last frame that wanted it soon (prefetch): evicted only for a tile a frame needs.
    last_kept: u64,
    /// Held children (a tile with children cannot go before them).
    children: u8,
}

pub struct HostCache {
    grid: Grid,
    budget: usize,
    /// Bytes a tile is charged at least ([`HostCache::limit_tiles`]), and the most tiles
    /// held: so that the cache never holds more tiles than the GPU atlas has layers.
    floor: usize,
    max_tiles: usize,
    bytes: usize,
    frame: u64,
    held: HashMap<TileKey, Held>,
    /// Tiles evicted since [`HostCache::drain_evicted`] was last called.
    evicted: Vec<TileKey>,
    pub stats: CacheStats,
}

impl HostCache {
    pub fn new(grid: Grid, budget_bytes: usize) -> Self {
        HostCache {
            grid,
            budget: budget_bytes,
            floor: 0,
            max_tiles: usize::MAX,
            bytes: 0,
            frame: 0,
            held: HashMap::new(),
            evicted: Vec::new(),
            stats: CacheStats::default(),
        }
    }

    /// Its byte budget (`--cache-mb`).
    pub fn budget(&self) -> usize {
        self.budget
    }

    /// Holds at most `tiles` tiles from now on (each charged at least `budget / tiles`
    /// bytes, rounded down so that `tiles` tiles no larger fit: rounded up, the last one
    /// never did; the count is checked too, for a budget whose remainder over `tiles`
    /// exceeds that share, which real tiles of 100 KB and more never meet): a frame
    /// draws only from held tiles, so every tile it draws from finds a layer in an atlas
    /// of that many layers. Leaves not used this frame are evicted until the tiles fit
    /// again.
    pub fn limit_tiles(&mut self, tiles: usize) {
        self.max_tiles = tiles.max(1);
        self.floor = self.budget / self.max_tiles;
        self.bytes = self.held.values().map(|h| self.charge(&h.data)).sum();
        while self.bytes > self.budget || self.held.len() > self.max_tiles {
            let frame = self.frame;
            let victim = self
                .evictable(true, None)
                .min_by_key(|(k, h)| (h.last_kept == frame, h.last_used, std::cmp::Reverse(k.level), **k))
                .map(|(k, _)| *k);
            match victim {
                Some(v) => self.evict(v),
                None => break,
            }
        }
    }

    /// The bytes a tile is charged: its decoded size, at least the floor.
    pub fn charge(&self, data: &TileData) -> usize {
        data.bytes.max(self.floor)
    }

    /// The least a tile is charged ([`HostCache::limit_tiles`]).
    pub fn floor(&self) -> usize {
        self.floor
    }

    /// Starts a frame: tiles used from now on are protected until the next call.
    pub fn begin_frame(&mut self) {
        self.frame += 1;
    }

    pub fn contains(&self, key: TileKey) -> bool {
        self.held.contains_key(&key)
    }

    /// The tile, without marking it used (the traversal reads; [`HostCache::mark_used`]
    /// protects what it used).
    pub fn peek(&self, key: TileKey) -> Option<&Arc<TileData>> {
        self.held.get(&key).map(|h| &h.data)
    }

    /// Marks tiles as used by the current frame: not evicted before the next frame.
    pub fn mark_used(&mut self, keys: impl IntoIterator<Item = TileKey>) {
        for k in keys {
            if let Some(h) = self.held.get_mut(&k) {
                h.last_used = self.frame;
            }
        }
    }

    /// Marks tiles as wanted soon by the current frame (prefetched): evicted this frame
    /// only to take in a tile a frame needs now.
    pub fn mark_kept(&mut self, keys: impl IntoIterator<Item = TileKey>) {
        for k in keys {
            if let Some(h) = self.held.get_mut(&k) {
                h.last_kept = self.frame;
            }
        }
    }

    pub fn len(&self) -> usize {
        self.held.len()
    }

    pub fn is_empty(&self) -> bool {
        self.held.is_empty()
    }

    pub fn bytes(&self) -> usize {
        self.bytes
    }

    /// The tiles [`HostCache::insert`] may evict now for a tile whose parent is
    /// `parent`: leaves not used this frame, not the parent, and unless the tile is
    /// `needed` now, not kept for prefetch this frame.
    fn evictable(&self, needed: bool, parent: Option<TileKey>) -> impl Iterator<Item = (&TileKey, &Held)> {
        let frame = self.frame;
        self.held.iter().filter(move |(k, h)| {
            h.children == 0 && h.last_used < frame && (needed || h.last_kept < frame) && Some(**k) != parent
        })
    }

    /// At least the bytes [`HostCache::insert`] can make room for now (free, plus the
    /// leaves it could evict this frame; evicting a leaf can make its parent one) for a
    /// tile with that parent (`needed`: a frame needs it now, so prefetched tiles may go too).
    pub fn room(&self, needed: bool, parent: Option<TileKey>) -> usize {
        let evictable: usize = self.evictable(needed, parent).map(|(_, h)| self.charge(&h.data)).sum();
        // With as many tiles as allowed, only what an eviction frees.
        let free = if self.held.len() < self.max_tiles { self.budget.saturating_sub(self.bytes) } else { 0 };
        free + evictable
    }

    /// Takes a tile in, evicting least recently used leaves not used this frame (and not
    /// its parent) until it fits: first those not kept for prefetch, then, for a tile a
    /// frame `needed`, kept ones. A tile already held is left as it is.
    pub fn insert(&mut self, data: Arc<TileData>, needed: bool) -> Result<(), Refused> {
        let key = data.key;
        if self.held.contains_key(&key) {
            return Ok(());
        }
        let parent = key.parent(self.grid.top);
        if let Some(p) = parent {
            if !self.held.contains_key(&p) {
                self.stats.refused_orphan += 1;
                return Err(Refused::NoParent);
            }
        }
        while self.bytes + self.charge(&data) > self.budget || self.held.len() >= self.max_tiles {
            let frame = self.frame;
            let victim = self
                .evictable(needed, parent)
                .min_by_key(|(k, h)| (h.last_kept == frame, h.last_used, std::cmp::Reverse(k.level), **k))
                .map(|(k, _)| *k);
            let Some(victim) = victim else {
                self.stats.refused_full += 1;
                return Err(Refused::Full);
            };
            self.evict(victim);
        }
        if let Some(p) = parent {
            self.held.get_mut(&p).expect("checked").children += 1;
        }
        self.bytes += self.charge(&data);
        self.held.insert(key, Held { data, last_used: self.frame, last_kept: self.frame, children: 0 });
        self.stats.inserted += 1;
        self.stats.peak_bytes = self.stats.peak_bytes.max(self.bytes);
        Ok(())
    }

    fn evict(&mut self, key: TileKey) {
        let gone = self.held.remove(&key).expect("held");
        debug_assert_eq!(gone.children, 0);
        self.bytes -= self.charge(&gone.data);
        if let Some(p) = key.parent(self.grid.top) {
            self.held.get_mut(&p).expect("ancestor-closed").children -= 1;
        }
        self.stats.evicted += 1;
        self.evicted.push(key);
    }

    /// The tiles evicted since the last call (their atlas layers may be reused).
    pub fn drain_evicted(&mut self) -> Vec<TileKey> {
        std::mem::take(&mut self.evicted)
    }

    /// The keys of every tile held, in no order.
    pub fn keys(&self) -> impl Iterator<Item = TileKey> + '_ {
        self.held.keys().copied()
    }

    /// Every tile held, coarsest first (each after its parent).
    pub fn tiles(&self) -> Vec<Arc<TileData>> {
        let mut t: Vec<Arc<TileData>> = self.held.values().map(|h| h.data.clone()).collect();
        t.sort_by_key(|d| (std::cmp::Reverse(d.key.level), d.key));
        t
    }

    /// The cache's invariants, for tests: ancestor-closed, child counts and bytes exact,
    /// within budget. Returns the first one broken.
    pub fn check(&self) -> Result<(), String> {
        let mut children: HashMap<TileKey, u8> = HashMap::new();
        for k in self.held.keys() {
            if let Some(p) = k.parent(self.grid.top) {
                if !self.held.contains_key(&p) {
                    return Err(format!("{k:?} is held without its parent {p:?}"));
                }
                *children.entry(p).or_default() += 1;
            }
        }
        for (k, h) in &self.held {
            if h.children != children.get(k).copied().unwrap_or(0) {
                return Err(format!("{k:?} counts {} children, holds {:?}", h.children, children.get(k)));
            }
        }
        let bytes: usize = self.held.values().map(|h| self.charge(&h.data)).sum();
        if bytes != self.bytes {
            return Err(format!("bytes {} counted, {bytes} held", self.bytes));
        }
        if self.bytes > self.budget {
            return Err(format!("{} bytes held over the budget of {}", self.bytes, self.budget));
        }
        Ok(())
    }
}

/// The block layout of an archive's grid: blocks of `block_quads + 1` vertices, one
/// root block over each top-level tile.
pub fn layout(grid: &Grid) -> BlockLayout {
    let m = grid.block_quads.trailing_zeros();
    let [nx, nz] = grid.tiles_at(grid.top);
    BlockLayout { n: root_lod(grid) + m, m, roots: [nx as usize, nz as usize] }
}

/// The samples of the tiles a cache holds, at integer sample coordinates: a sample is
/// read from the finest held tile whose vertices include it. Every level holds the same
/// value at a sample (tiles are subsampled, not filtered; beyond the true extent they
/// repeat its edge at every level), so this is the value the shader fetches from the
/// block's own tile. `NaN` where no held tile has the sample: a drawn block never asks
/// for one (its tile and its coarser neighbours' are held), and tests look for it.
pub struct Resident<'a> {
    pub grid: &'a Grid,
    pub cache: &'a HostCache,
}

impl Resident<'_> {
    /// The finest held tile whose vertices include sample `(x, z)`, and the vertex.
    fn holding(&self, x: i64, z: i64) -> Option<(&TileData, usize, usize)> {
        if x < 0 || z < 0 {
            return None;
        }
        let finest = (x.trailing_zeros().min(z.trailing_zeros()) as u8).min(self.grid.top);
        for level in 0..=finest {
            let span = self.grid.tile_span(level) as i64;
            // A sample on a tile border is in both tiles; either will do.
            let candidates = |c: i64| [Some(c / span), (c % span == 0 && c > 0).then(|| c / span - 1)];
            for tz in candidates(z).into_iter().flatten() {
                for tx in candidates(x).into_iter().flatten() {
                    let key = TileKey::new(level, tx as u32, tz as u32);
                    if let Some(tile) = self.cache.peek(key) {
                        let (i, j) = ((x - tx * span) >> level, (z - tz * span) >> level);
                        return Some((tile, i as usize, j as usize));
                    }
                }
            }
        }
        None
    }

    /// Whether sample `(x, z)` is a void drawn as a hole, as the held tiles say (`false`
    /// where none holds it; samples beyond the true extent repeat its edge, as heights).
    pub fn is_hole(&self, x: i64, z: i64) -> bool {
        let (x, z) = (x.clamp(0, self.grid.width as i64 - 1), z.clamp(0, self.grid.height as i64 - 1));
        self.holding(x, z).is_some_and(|(tile, i, j)| tile.void(i, j))
    }
}

impl RawSamples for Resident<'_> {
    fn raw_at(&self, x: i64, z: i64) -> f32 {
        self.holding(x, z).map_or(f32::NAN, |(tile, i, j)| tile.vertex(i, j))
    }
}
