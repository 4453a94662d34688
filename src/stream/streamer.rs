//! One frame of streaming, in the order that keeps the rules: take what the IO thread
//! read (protecting the previous frame's tiles from eviction), select over what is held,
//! protect what the selection used, ask for what it wants (most wanted first).

use super::cache::{tile_bytes_estimate, HostCache, Refused, TileData};
use super::errors::TileErrors;
use super::io::{Io, Loaded, TileSource};
use super::morph;
use super::traverse::{select_by, Selection, StreamedLod, StripCache, View};
use super::{Grid, TileKey};
use crate::lod::block::TraversalPool;
use crate::lod::gie::ErrorMode;
use crate::lod::morph::MorphRule;
use foldhash::{HashMap, HashMapExt, HashSet, HashSetExt};
use std::sync::atomic::AtomicBool;
use std::sync::Arc;

/// Frames after which a tile that failed to read is asked for again (a file that comes
/// back is used again; one that stays damaged is not read every frame).
pub const RETRY_FRAMES: u64 = 64;
/// Frames before a tile the full cache refused is asked for again.
pub const FULL_BACKOFF_FRAMES: u64 = 8;
/// `--refresh-at`'s default: new errors are asked for once the camera has moved this
/// fraction of the distance to the nearest block since they were computed.
pub const DEFAULT_REFRESH_AT: f32 = 0.05;

/// What a streamed run did, for summary.json and the panel.
#[derive(Clone, Debug, Default, PartialEq, serde::Serialize)]
pub struct StreamStats {
    pub frames: u64,
    /// Frames where a block that should split was drawn as it was (its tile not held),
    /// or the top tile was not held.
    pub frames_over_bound: u64,
    /// The largest error / delta of a block drawn over the bound (1 when none was).
    pub worst_factor: f32,
    pub tiles_loaded: u64,
    /// Different tiles loaded, and what they take decoded (a flight over more than the
    /// cache holds evicts and reloads).
    pub distinct_tiles: u64,
    pub distinct_bytes: u64,
    pub tiles_evicted: u64,
    pub tiles_failed: u64,
    /// Compressed bytes read for the tiles loaded.
    pub bytes_read: u64,
    /// Tiles read but not taken: the cache was full of needed tiles, or the parent had
    /// gone.
    pub refused_full: u64,
    pub refused_orphan: u64,
    pub peak_cache_bytes: usize,
}

/// Where tiles read wait before the host cache takes them (SPEC section 8, "Residency"):
/// with a GPU, the errors activity uploads them into the atlas and hands them back once
/// their generation has finished, so that every tile the traversal can select is
/// drawable ([`crate::errors::atlas::AtlasFeed`]).
pub trait TileGate: Send {
    /// Tiles read, with the bytes read for each, in the order read.
    fn send(&self, tiles: Vec<(Arc<TileData>, u64)>);
    /// Tiles now drawable, in the order sent; and tiles that found no room (asked for
    /// again later).
    fn take(&self) -> (Vec<(Arc<TileData>, u64)>, Vec<TileKey>);
    /// Tiles the host cache no longer holds: their room may be reused.
    fn release(&self, keys: Vec<TileKey>);
    /// Waits until every tile sent is drawable or refused (or the gate has failed).
    fn wait(&self);
    /// Asks the errors activity for the block errors of `tiles` at `view` (replacing a
    /// request not started yet). A gate without an errors activity ignores it.
    fn request_errors(&self, _view: View, _tiles: Vec<TileKey>, _height_scale: f64, _mode: ErrorMode) {}
    /// The newest finished generation of block errors, if any.
    fn errors(&self) -> Option<Arc<TileErrors>> {
        None
    }
    /// Waits until every request for errors made so far is answered.
    fn wait_errors(&self) {}
}

/// A request for block errors ([`TileGate::request_errors`]), numbered in order.
#[derive(Clone, Debug)]
pub struct ErrorsRequest {
    pub number: u64,
    pub view: View,
    pub tiles: Vec<TileKey>,
    /// The terrain's height scale now (the exaggeration changes it).
    pub height_scale: f64,
    /// The error mode to shade in (`--error-mode`).
    pub mode: ErrorMode,
}

/// What a request for errors was made for: the camera, the tiles, the tiles held then,
/// the height scale's bits and the mode (the same again gets the same answer).
type ErrorsAsked = (glam::DVec3, Vec<TileKey>, usize, (u64, ErrorMode));

pub struct Streamer {
    pub grid: Grid,
    pub cache: HostCache,
    io: Io,
    /// What the IO thread reads from (also read directly for whole levels: the lighting map).
    source: Arc<dyn TileSource>,
    pub stats: StreamStats,
    /// Tiles not asked for again before the frame given: they failed to read, or the
    /// cache had no room for them.
    backoff: HashMap<TileKey, u64>,
    seen: HashSet<TileKey>,
    priority: HashMap<TileKey, f32>,
    /// The first failure's message (a damaged or missing file), for the run's report.
    pub first_failure: Option<String>,
    /// What stitching costs each block configuration drawn (archive data: kept).
    strips: StripCache,
    /// How drawn blocks morph ([`crate::stream::morph`]); `None`: they do not (`--morph
    /// off`).
    pub morph: Option<MorphRule>,
    /// How blocks choose their LOD (`--lod`); only the bound's selection morphs.
    pub lod: StreamedLod,
    /// The error the bound's selection compares with delta (`--error-mode`): strict, or
    /// the paper's estimate from the errors activity where it has one.
    pub error_mode: ErrorMode,
    /// The GPU atlas's way in, once attached.
    gate: Option<Box<dyn TileGate>>,
    /// Tiles sent through the gate and not back yet (not asked for again).
    gated: HashSet<TileKey>,
    /// Threads for the per-block morph terms (`--traversal-threads`; none: the caller's).
    pool: TraversalPool,
    /// A stop request (a signal's flag): [`Streamer::settle`] returns when it is set,
    /// whatever tiles are still being read.
    pub stop: Option<Arc<AtomicBool>>,
    /// New errors are asked for once the camera has moved this fraction of the distance
    /// to the nearest block since they were computed (`--refresh-at`).
    pub refresh_at: f32,
    /// The last request for errors: the camera, the tiles, the tiles held then, the
    /// height scale's bits.
    errors_asked: Option<ErrorsAsked>,
}

impl Streamer {
    /// Where tiles come from.
    pub fn source(&self) -> &Arc<dyn TileSource> {
        &self.source
    }

    pub fn new(source: Arc<dyn TileSource>, grid: Grid, cache_bytes: usize) -> Self {
        Streamer {
            grid,
            cache: HostCache::new(grid, cache_bytes),
            io: Io::spawn(source.clone(), grid),
            source,
            stats: StreamStats { worst_factor: 1.0, ..Default::default() },
            backoff: HashMap::new(),
            seen: HashSet::new(),
            priority: HashMap::new(),
            first_failure: None,
            // Four times the blocks of a frame to the horizon (about 4,000): the blocks a
            // flight keeps drawing are never measured again.
            strips: StripCache::with_entries(1 << 15),
            morph: Some(MorphRule::Bounded),
            lod: StreamedLod::Error,
            error_mode: ErrorMode::Strict,
            gate: None,
            gated: HashSet::new(),
            pool: TraversalPool::default(),
            stop: None,
            refresh_at: DEFAULT_REFRESH_AT,
            errors_asked: None,
        }
    }

    /// Computes each frame's per-block morph terms on `threads` threads of its own (1:
    /// on the caller's); the frames are the same on any number.
    pub fn set_threads(&mut self, threads: usize) -> Result<(), String> {
        self.pool = TraversalPool::new(threads)?;
        Ok(())
    }

    /// The threads [`Streamer::set_threads`] gave the morph terms.
    pub fn threads(&self) -> usize {
        self.pool.threads()
    }

    /// From now on tiles read go through `gate` (the GPU atlas) before the cache takes
    /// them, and the cache holds at most `tiles` tiles. What it holds already is sent
    /// through first, and waited for.
    pub fn attach(&mut self, gate: Box<dyn TileGate>, tiles: usize) {
        self.cache.limit_tiles(tiles);
        self.cache.drain_evicted(); // never in this gate
        gate.send(self.cache.tiles().into_iter().map(|t| (t, 0)).collect());
        gate.wait();
        let (_, refused) = gate.take();
        if !refused.is_empty() {
            tracing::warn!("streaming: {} held tiles found no atlas layer", refused.len());
        }
        self.gate = Some(gate);
    }

    /// Tiles read pass through the gate, if any: sent, then what came back (waiting for
    /// all of it when `wait`). Tiles refused are asked for again later.
    fn through_gate(&mut self, loaded: Vec<Loaded>, wait: bool) -> Vec<Loaded> {
        let Some(gate) = &self.gate else { return loaded };
        let mut out = Vec::new();
        let mut tiles = Vec::new();
        for l in loaded {
            match l {
                Loaded::Tile { data, bytes_read } => {
                    self.gated.insert(data.key);
                    tiles.push((data, bytes_read));
                }
                other => out.push(other),
            }
        }
        gate.send(tiles);
        if wait {
            gate.wait();
        }
        let (back, refused) = gate.take();
        for k in refused {
            self.gated.remove(&k);
            self.backoff.insert(k, self.stats.frames + FULL_BACKOFF_FRAMES);
        }
        for (data, bytes_read) in back {
            self.gated.remove(&data.key);
            out.push(Loaded::Tile { data, bytes_read });
        }
        out
    }

    fn take(&mut self, loaded: Vec<Loaded>) {
        let mut refused = Vec::new();
        for l in loaded {
            match l {
                Loaded::Tile { data, bytes_read } => {
                    self.stats.bytes_read += bytes_read;
                    self.stats.tiles_loaded += 1;
                    if self.seen.insert(data.key) {
                        self.stats.distinct_tiles += 1;
                        self.stats.distinct_bytes += data.bytes as u64;
                    }
                    let key = data.key;
                    let needed = self.priority.get(&key).is_some_and(|p| *p > 1.0);
                    match self.cache.insert(data, needed) {
                        Ok(()) => {}
                        Err(Refused::NoParent) => refused.push(key),
                        // The frame's tiles fill the budget: asking again at once would
                        // read it again and again.
                        Err(Refused::Full) => {
                            self.backoff.insert(key, self.stats.frames + FULL_BACKOFF_FRAMES);
                            refused.push(key);
                        }
                    }
                }
                Loaded::Absent(_) => {}
                Loaded::Failed(key, message) => {
                    self.stats.tiles_failed += 1;
                    self.backoff.insert(key, self.stats.frames + RETRY_FRAMES);
                    if self.first_failure.is_none() {
                        tracing::warn!("streaming: {message} (drawn coarser; retried in {RETRY_FRAMES} frames)");
                        self.first_failure = Some(message);
                    }
                }
            }
        }
        // What the cache let go (or never took) frees its atlas layer.
        refused.extend(self.cache.drain_evicted());
        if let Some(gate) = &self.gate {
            gate.release(refused);
        }
        let c = self.cache.stats;
        (self.stats.tiles_evicted, self.stats.refused_full, self.stats.refused_orphan, self.stats.peak_cache_bytes) =
            (c.evicted, c.refused_full, c.refused_orphan, c.peak_bytes);
    }

    /// One frame at `view`; `ahead` (the camera where it will be soon) adds the tiles it
    /// wants at a lower priority (they are not protected: the current frame's are).
    pub fn frame(&mut self, view: &View, ahead: Option<&View>, delta: f32, prefetch: f32) -> Selection {
        let arrived = self.io.arrived();
        let arrived = self.through_gate(arrived, false);
        self.take(arrived);
        self.cache.begin_frame();
        self.stats.frames += 1;
        // A generation of the other mode bounds nothing here.
        let errors = self.gate.as_ref().and_then(|g| g.errors()).filter(|e| e.mode == self.error_mode);
        let mut sel = select_by(
            &self.grid,
            &self.cache,
            view,
            (self.lod, delta, self.error_mode),
            prefetch,
            Some(&self.strips),
            errors.as_deref(),
        );
        if let Some(rule) = self.morph.filter(|_| self.lod == StreamedLod::Error) {
            let (grid, cache, strips) = (&self.grid, &self.cache, &self.strips);
            sel.morphing = self.pool.install(|| morph::assign(grid, cache, strips, view, delta, &mut sel, rule));
        }
        self.cache.mark_used(sel.used.iter().copied());
        self.cache.mark_kept(sel.kept.iter().copied());
        let mut wanted = sel.wanted.clone();
        if let Some(a) = ahead {
            let rule = (self.lod, delta, self.error_mode);
            let next = select_by(&self.grid, &self.cache, a, rule, prefetch, None, errors.as_deref());
            self.cache.mark_kept(next.used.iter().chain(&next.kept).copied());
            // Below every tile the current frame needs.
            wanted.extend(next.wanted.iter().map(|&(k, p)| (k, p.min(1.0) * 0.5)));
        }
        self.request(wanted);
        self.request_errors(view, &sel, errors.as_deref());
        if !sel.within_bound() {
            self.stats.frames_over_bound += 1;
        }
        if sel.over_bound > 0 {
            self.stats.worst_factor = self.stats.worst_factor.max(sel.worst_factor);
        }
        sel
    }

    /// Asks the errors activity for a new generation when the selection needs one: some
    /// block that could have had an error from it had none, or the camera has moved more
    /// than [`Streamer::refresh_at`] of some block's distance since. The tiles: those the selection visited, and the finer tiles
    /// of its drawn blocks that are held (where it splits next).
    fn request_errors(&mut self, view: &View, sel: &Selection, errors: Option<&TileErrors>) {
        if self.lod != StreamedLod::Error {
            return;
        }
        // A move of `refresh_at` of a block's distance grows its error by 1 / (1 - it).
        let refresh = 1.0 / (1.0 - self.refresh_at.clamp(0.0, 0.99));
        let needed = errors.is_none() || sel.errors_from_tiles > 0 || sel.errors_stale_worst > refresh;
        if needed {
            self.ask_errors(view, sel);
        }
    }

    /// Asks the errors activity for a generation at `view` over the tiles `sel` (made at
    /// that view) reaches, needed or not (`errors` runs generations so), unless the same
    /// was asked last. Nothing without an errors activity.
    pub fn ask_errors(&mut self, view: &View, sel: &Selection) {
        let Some(gate) = self.gate.as_ref() else { return };
        let mut tiles: HashSet<TileKey> = match self.error_mode {
            ErrorMode::Strict => sel.used.iter().copied().filter(|k| k.level > 0).collect(),
            // A block's paper error takes the max over every finer level (eq. 4): every
            // tile held, so that each block's descendants that are resident count.
            ErrorMode::Paper => self.cache.keys().collect(),
        };
        for b in sel.blocks.iter().filter(|b| b.lod > 1) {
            let finer = super::cache::serving_tile(&self.grid, b.lod - 1, 2 * b.bx, 2 * b.bz);
            if self.cache.contains(finer) {
                tiles.insert(finer);
            }
        }
        let mut tiles: Vec<TileKey> = tiles.into_iter().collect();
        tiles.sort();
        // The same request again would get the same answer (a tile not resident when it
        // was shaded may be now: the tiles held are part of it).
        let asked =
            (view.position, tiles.clone(), self.cache.len(), (self.grid.height_scale.to_bits(), self.error_mode));
        if self.errors_asked.as_ref() == Some(&asked) {
            return;
        }
        self.errors_asked = Some(asked);
        gate.request_errors(*view, tiles, self.grid.height_scale, self.error_mode);
    }

    fn request(&mut self, mut wanted: Vec<(TileKey, f32)>) {
        let frame = self.stats.frames;
        self.backoff.retain(|_, retry| *retry > frame);
        wanted.retain(|(k, _)| !self.cache.contains(*k) && !self.gated.contains(k) && !self.backoff.contains_key(k));
        wanted.sort_by(|a, b| b.1.total_cmp(&a.1).then(a.0.cmp(&b.0)));
        // Only what the cache could take: the rest would be read and refused.
        let (mut room_needed, mut room_soon) = (self.cache.room(true, None), self.cache.room(false, None));
        let mut once = HashSet::new();
        wanted.retain(|w| once.insert(w.0)); // the first is the highest priority
        wanted.retain(|&(k, p)| {
            let size = tile_bytes_estimate(&self.grid, k.level).max(self.cache.floor());
            let room = if p > 1.0 { &mut room_needed } else { &mut room_soon };
            let fits = size <= *room;
            if fits {
                room_needed = room_needed.saturating_sub(size);
                room_soon = room_soon.saturating_sub(size);
            }
            fits
        });
        let keys: Vec<TileKey> = wanted.iter().map(|w| w.0).collect();
        // The highest priority each tile was asked for with (a tile a frame needs may
        // evict prefetched ones when it arrives).
        self.priority.clear();
        for &(k, p) in wanted.iter().rev() {
            self.priority.insert(k, p);
        }
        self.io.request(&keys);
    }

    /// Whether block errors come from an errors activity (a GPU atlas is attached).
    pub fn has_errors_activity(&self) -> bool {
        self.gate.is_some()
    }

    /// Holds at most `tiles` tiles (the GPU atlas's layers): [`HostCache::limit_tiles`].
    pub fn limit_tiles(&mut self, tiles: usize) {
        self.cache.limit_tiles(tiles);
    }

    /// The terrain's height (world units) under world `(x, z)` from the finest held tile
    /// covering it (nearest vertex); `None` outside the terrain or before the top tile
    /// arrives.
    pub fn ground(&self, wx: f64, wz: f64) -> Option<f64> {
        let [sx, sz] = self.grid.sample_of(wx, wz);
        if !(sx >= 0.0 && sz >= 0.0 && sx <= (self.grid.width - 1) as f64 && sz <= (self.grid.height - 1) as f64) {
            return None;
        }
        (0..=self.grid.top).find_map(|level| {
            let span = self.grid.tile_span(level) as f64;
            let key = TileKey::new(level, (sx / span) as u32, (sz / span) as u32);
            let tile = self.cache.peek(key)?;
            let step = f64::from(1u32 << level);
            let (i, j) =
                (((sx - f64::from(key.tx) * span) / step).round(), ((sz - f64::from(key.tz) * span) / step).round());
            let h = tile.vertex(i as usize, j as usize);
            Some(f64::from(h) * self.grid.height_scale)
        })
    }

    /// Whether a stop was asked for ([`Streamer::stop`]).
    pub fn stopped(&self) -> bool {
        self.stop.as_ref().is_some_and(|s| s.load(std::sync::atomic::Ordering::SeqCst))
    }

    /// Waits until the IO thread has read everything asked for (and the gate has passed
    /// it) and takes it, and until the errors asked for are shaded (runs that measure a
    /// settled frame, and tests), or until a stop is asked for.
    pub fn settle(&mut self) {
        loop {
            let got = self.io.wait(self.stop.as_deref());
            let idle = got.is_empty() && self.io.outstanding() == 0;
            let got = self.through_gate(got, true);
            self.take(got);
            if idle || self.stopped() {
                if let Some(gate) = &self.gate {
                    gate.wait_errors();
                }
                return;
            }
        }
    }
}
