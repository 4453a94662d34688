//! The heightfield atlas of streamed frames and the errors activity that fills it (SPEC
//! section 8, "Residency" and "Budgets"): one array image, a tile's heights (its
//! one-sample border included) in each layer. Tiles the IO thread read are handed to the
//! errors activity's thread ([`AtlasFeed`], the streamer's end), which uploads them on
//! the errors queue, one generation a batch, and hands them back once the generation has
//! finished: only then does the host cache take them, so the traversal selects only tiles
//! the draw thread can draw. Layers are handed out and reused under [`AtlasLayers`]'
//! rules: a layer is rewritten only once every frame that drew from it has completed (the
//! draw queue's timeline, read, never waited on) and the host cache has let its tile go.
//! Tiles bring their groups' deviations `D` from the archive (computed by `prepare`),
//! uploaded beside the heights; on request the same thread shades the blocks' errors
//! from them over the atlas ([`AtlasPasses`]) and publishes each finished generation
//! ([`TileErrors`]) for the traversal.

use crate::errors::activity::HOST_LOOK_NS;
use crate::errors::atlas_passes::{AtlasPasses, Shaded};
use crate::errors::handoff::{AtlasLayers, Handoff};
use crate::lod::gie::ErrorMode;
use crate::stream::cache::{Heights, TileData};
use crate::stream::errors::TileErrors;
use crate::stream::streamer::{ErrorsRequest, TileGate};
use crate::stream::traverse::View;
use crate::stream::{Grid, TileKey};
use crate::trace::{Trace, ERRORS_TID};
use crate::vk::{
    image_barrier, vk, Buffer, CommandPool, Device, Image, TimelineSemaphore, VkError, VkResult, VkResultExt,
};
use std::collections::HashSet;
use std::sync::{Arc, Condvar, Mutex};
use std::thread::JoinHandle;
use std::time::Instant;

/// The most layers an atlas takes, whatever the budget (llvmpipe's limit).
pub const MAX_LAYERS: u32 = 2048;

/// The atlas budget, MB, of a terrain with more tiles than [`MAX_LAYERS`] when none is
/// given ([`HeightAtlas::default_budget_mb`]).
pub const DEFAULT_BUDGET_MB: u32 = 256;
/// Layers of heights per slot of deviations: tiles above level 0, the only ones with a
/// `D`, are about a quarter of a quadtree's and a third of what a flight holds. A tile
/// that finds no slot is drawn, its blocks bounded by its summary alone.
pub const DEVIATION_SHARE: u32 = 2;

/// The share of wall time the errors generations take at most unless told
/// (`--update-share`'s default).
pub const DEFAULT_UPDATE_SHARE: f32 = 0.05;

/// A tile read by the IO thread and the bytes read for it.
pub type Read = (Arc<TileData>, u64);

/// A tile given a layer of heights and, above level 0, a slot of deviations.
type Placed = (Arc<TileData>, usize, Option<u32>);

/// What the two threads share, under one lock.
struct State {
    layers: AtlasLayers<TileKey>,
    /// The newest generation finished: the tiles it uploaded are drawable.
    finished: u64,
    /// Tiles for the errors thread, in the order read.
    todo: Vec<Read>,
    /// Tiles of finished generations (or found in the atlas already), for the streamer.
    done: Vec<Read>,
    /// Tiles that found no layer (every one is held by the cache or drawn by a frame not
    /// completed yet): the streamer asks for them again later.
    dropped: Vec<TileKey>,
    /// Tiles the host cache let go: their layers may be rewritten (once the frames that
    /// drew them completed). Every other resident tile is protected.
    released: HashSet<TileKey>,
    /// Tiles handed over and neither done nor dropped yet.
    busy: usize,
    stop: bool,
    failure: Option<String>,
    uploaded: Uploaded,
    /// The deviation slot of the tile each layer holds.
    slots: DeviationSlots,
    /// The newest request for block errors not started yet, and the number of the last
    /// one made and of the last one answered (shaded, or found nothing to shade).
    request: Option<ErrorsRequest>,
    requested: u64,
    answered: u64,
    /// The newest generation of block errors.
    errors: Option<Arc<TileErrors>>,
    shaded: ErrorsShaded,
    /// Every block error read back is multiplied by this (1; tests corrupt it).
    scale_errors: f32,
    /// Test hook: block-error generation number this fails with ERROR_DEVICE_LOST (0: never).
    device_lost_at: u64,
    /// The largest share of wall time the errors generations take (`--update-share`),
    /// when the next may start, and whether a settle waits for the request (it starts
    /// at once then).
    update_share: f32,
    next_errors_at: Option<Instant>,
    hurry: bool,
    /// The most generations the errors thread had in flight at once.
    most_in_flight: u64,
}

/// Which slot of deviations the tile in each layer of heights holds (tiles above level 0
/// only, while a slot is free): a layer's new tile takes over from its old one, whose
/// slot is freed first.
#[derive(Clone, Debug, PartialEq, Eq)]
struct DeviationSlots {
    of_layer: Vec<Option<u32>>,
    free: Vec<u32>,
}

impl DeviationSlots {
    fn new(layers: usize, slots: u32) -> Self {
        DeviationSlots { of_layer: vec![None; layers], free: (0..slots).rev().collect() }
    }

    /// A new tile in `layer`: the old one's slot is freed, and the new one takes a free
    /// slot if it `wants` one (it has a `D`).
    fn place(&mut self, layer: usize, wants: bool) -> Option<u32> {
        if let Some(old) = self.of_layer[layer].take() {
            self.free.push(old);
        }
        if wants {
            self.of_layer[layer] = self.free.pop();
        }
        self.of_layer[layer]
    }

    fn of(&self, layer: usize) -> Option<u32> {
        self.of_layer[layer]
    }
}

/// What the errors generations over the atlas shaded, in all.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct ErrorsShaded {
    pub generations: u64,
    pub tiles: u64,
    pub groups: u64,
    pub bytes_read_back: u64,
    /// Each generation's GPU time (empty without timestamps).
    pub gpu_ms: Vec<f64>,
    /// The last generation's figures.
    pub last: Option<Shaded>,
}

impl ErrorsShaded {
    fn add(&mut self, s: &Shaded) {
        self.generations += 1;
        self.tiles += s.tiles;
        self.groups += s.groups;
        self.bytes_read_back += s.bytes_read_back;
        self.gpu_ms.extend(s.gpu_ms);
        self.last = Some(*s);
    }
}

/// What the errors thread uploaded.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct Uploaded {
    pub tiles: u64,
    pub bytes: u64,
    pub generations: u64,
    /// Tiles that found no layer and were asked for again.
    pub dropped: u64,
}

struct Shared {
    /// Declared first: dropped after the thread that writes them has been joined.
    image: Image,
    /// The tiles' group deviations `D` (R16_SFLOAT, rounded up), one tile a layer: a slot
    /// for every [`DEVIATION_SHARE`] layers of `image`, held by tiles above level 0
    /// while their layer holds them (level 0's blocks never split).
    deviation: Image,
    grid: Grid,
    side: u32,
    unorm16: bool,
    state: Mutex<State>,
    /// Wakes the errors thread: work or stop.
    work: Condvar,
    /// Wakes the streamer waiting for a batch ([`AtlasFeed::wait`]).
    progress: Condvar,
    /// Generation `g` is written when this reaches `g` (the errors queue signals it).
    generations: TimelineSemaphore,
    /// Frame `f` has completed when this reaches `f` (the draw queue signals it).
    frames: TimelineSemaphore,
    /// Each generation is waited for before the next is recorded (`--error-pacing`).
    paced: std::sync::atomic::AtomicBool,
}

impl Shared {
    fn lock(&self) -> std::sync::MutexGuard<'_, State> {
        // A panic on the other thread leaves the state consistent (each change is made
        // whole under the lock): go on with it.
        self.state.lock().unwrap_or_else(|e| e.into_inner())
    }
}

/// The atlas and the errors activity's thread that uploads into it (the draw thread's
/// end). Dropping it stops the thread and waits for it.
pub struct HeightAtlas {
    shared: Arc<Shared>,
    thread: Option<JoinHandle<()>>,
}

/// The streamer's end of the atlas: tiles read go in, drawable tiles come out.
pub struct AtlasFeed {
    shared: Arc<Shared>,
}

impl HeightAtlas {
    /// Bytes of one layer of heights: a tile's heights with their one-sample border
    /// (and with holes, whether each is a void).
    fn height_layer_bytes(grid: &Grid) -> u64 {
        let side = (grid.tile_quads + 3) as u64;
        side * side * grid.atlas_texel_bytes() as u64
    }

    /// Bytes of one slot of deviations: a tile's groups' `D` (half floats).
    fn deviation_slot_bytes(grid: &Grid) -> u64 {
        let groups = grid.tile_quads as u64;
        groups * groups * 2
    }

    /// Staging bytes of one tile: its heights, then its deviations.
    fn staged_bytes(grid: &Grid) -> usize {
        (Self::height_layer_bytes(grid) + Self::deviation_slot_bytes(grid)) as usize
    }

    /// What one layer costs of the budget: its heights and its share of a slot of
    /// deviations ([`DEVIATION_SHARE`]).
    pub fn layer_bytes(grid: &Grid) -> u64 {
        Self::height_layer_bytes(grid) + Self::deviation_slot_bytes(grid).div_ceil(u64::from(DEVIATION_SHARE))
    }

    /// The default atlas budget for `grid`, MB: every tile of the terrain when they fit
    /// [`MAX_LAYERS`] with the layers that take tiles on their way in
    /// ([`Self::cache_tiles`]): a file that fits in memory is then drawn wholly resident,
    /// never over the bound for want of a layer (an f32 8193^2 is 1,365 tiles), and a
    /// small one takes no more than it needs. [`DEFAULT_BUDGET_MB`] for a terrain with
    /// more tiles.
    pub fn default_budget_mb(grid: &Grid) -> u32 {
        let tiles: u64 = (0..=grid.top).map(|l| grid.tiles_at(l).iter().map(|&n| u64::from(n)).product::<u64>()).sum();
        let Some(layers) = (tiles..=u64::from(MAX_LAYERS)).find(|&l| Self::cache_tiles(l as u32) as u64 >= tiles)
        else {
            return DEFAULT_BUDGET_MB;
        };
        (layers * Self::layer_bytes(grid)).div_ceil(1 << 20) as u32
    }

    /// The layers an atlas of `budget_bytes` has on a device allowing `device_limit`
    /// array layers (at most [`MAX_LAYERS`]).
    pub fn layers_for(grid: &Grid, budget_bytes: u64, device_limit: u32) -> u32 {
        (budget_bytes / Self::layer_bytes(grid)).min(u64::from(device_limit.min(MAX_LAYERS))) as u32
    }

    /// The tiles the host cache may hold with an atlas of `layers`: the other layers take
    /// tiles on their way in (uploaded, not taken yet), so the errors thread finds a layer
    /// the cache does not hold while the cache is full.
    pub fn cache_tiles(layers: u32) -> usize {
        let layers = layers as usize;
        layers.saturating_sub((layers / 8).clamp(1, 256)).max(1)
    }

    /// An atlas for `grid`'s tiles within `budget_bytes` of device memory (as many layers
    /// as fit, at most the device's `maxImageArrayLayers` and [`MAX_LAYERS`]), and the
    /// errors activity's thread that fills it.
    pub fn new(device: &Arc<Device>, grid: &Grid, budget_bytes: u64) -> VkResult<Self> {
        Self::traced(device, grid, budget_bytes, Trace::off())
    }

    /// [`HeightAtlas::new`], its thread's uploads recorded in `trace` (one span a
    /// generation, on the errors activity's track).
    pub fn traced(device: &Arc<Device>, grid: &Grid, budget_bytes: u64, trace: Trace) -> VkResult<Self> {
        let side = (grid.tile_quads + 3) as u32;
        let unorm16 = grid.height_bytes == 2;
        let layer_bytes = Self::layer_bytes(grid);
        let layers = Self::layers_for(grid, budget_bytes, device.properties.limits.max_image_array_layers);
        if layers == 0 {
            return Err(VkError::Setup(format!(
                "--gpu-mb: {budget_bytes} bytes hold no atlas layer ({layer_bytes} bytes a tile)"
            )));
        }
        // With holes, a second channel says whether the height is a void (every shader
        // reads heights from the first).
        let format = match (unorm16, grid.holes) {
            (true, false) => vk::Format::R16_UNORM,
            (false, false) => vk::Format::R32_SFLOAT,
            (true, true) => vk::Format::R16G16_UNORM,
            (false, true) => vk::Format::R32G32_SFLOAT,
        };
        let usage =
            vk::ImageUsageFlags::SAMPLED | vk::ImageUsageFlags::TRANSFER_DST | vk::ImageUsageFlags::TRANSFER_SRC;
        let extent = vk::Extent2D { width: side, height: side };
        // Shared: written on the errors queue, sampled on the draw queue.
        let image = Image::array(device, "heightfield atlas", extent, format, layers, usage, true)?;
        let groups = vk::Extent2D { width: grid.tile_quads as u32, height: grid.tile_quads as u32 };
        let usage = vk::ImageUsageFlags::SAMPLED | vk::ImageUsageFlags::TRANSFER_DST;
        let slots = layers.div_ceil(DEVIATION_SHARE);
        let deviation = Image::array(device, "deviation atlas", groups, vk::Format::R16_SFLOAT, slots, usage, true)?;
        {
            // Every layer starts readable (a draw's descriptor covers all of them), before
            // either activity uses the image.
            let pool = CommandPool::new(device, device.draw_queue.family)?;
            let range = image.range(0, 1);
            device.one_shot(&pool, |cmd| {
                let undefined = (vk::PipelineStageFlags2::NONE, vk::AccessFlags2::NONE, vk::ImageLayout::UNDEFINED);
                // SAFETY: `cmd` is recording; the images outlive one_shot's wait.
                unsafe {
                    image_barrier(&device.raw, cmd, image.handle, range, undefined, SAMPLED);
                    image_barrier(&device.raw, cmd, deviation.handle, deviation.range(0, 1), undefined, SAMPLED);
                }
            })?;
        }
        let shared = Arc::new(Shared {
            image,
            deviation,
            grid: *grid,
            side,
            unorm16,
            state: Mutex::new(State {
                layers: AtlasLayers::new(layers as usize),
                finished: 0,
                todo: Vec::new(),
                done: Vec::new(),
                dropped: Vec::new(),
                released: HashSet::new(),
                busy: 0,
                stop: false,
                failure: None,
                uploaded: Uploaded::default(),
                slots: DeviationSlots::new(layers as usize, slots),
                request: None,
                requested: 0,
                answered: 0,
                errors: None,
                shaded: ErrorsShaded::default(),
                scale_errors: 1.0,
                device_lost_at: 0,
                update_share: DEFAULT_UPDATE_SHARE,
                next_errors_at: None,
                hurry: false,
                most_in_flight: 0,
            }),
            work: Condvar::new(),
            progress: Condvar::new(),
            generations: TimelineSemaphore::new(device, 0)?,
            frames: TimelineSemaphore::new(device, 0)?,
            paced: std::sync::atomic::AtomicBool::new(true),
        });
        let thread = std::thread::Builder::new()
            .name("vkterrain-atlas".into())
            .spawn({
                let (device, shared) = (device.clone(), shared.clone());
                move || {
                    if let Err(e) = run(&device, &shared, &trace) {
                        let mut s = shared.lock();
                        // The thread is the errors activity: its first pass uploads tiles.
                        s.failure = Some(format!("errors activity: {e}"));
                        s.busy = 0;
                        drop(s);
                        shared.progress.notify_all();
                    }
                }
            })
            .map_err(|e| VkError::Setup(format!("cannot start the atlas thread: {e}")))?;
        Ok(HeightAtlas { shared, thread: Some(thread) })
    }

    /// The streamer's end: tiles read go in, and come back once drawable.
    pub fn feed(&self) -> AtlasFeed {
        AtlasFeed { shared: self.shared.clone() }
    }

    pub fn layer_count(&self) -> u32 {
        self.shared.image.layers
    }

    /// Bytes of its images: every layer of heights and every slot of deviations.
    pub fn bytes(&self) -> u64 {
        let grid = &self.shared.grid;
        u64::from(self.shared.image.layers) * Self::height_layer_bytes(grid)
            + u64::from(self.shared.deviation.layers) * Self::deviation_slot_bytes(grid)
    }

    pub fn image(&self) -> &Image {
        &self.shared.image
    }

    /// Samples a side of a layer (the tile side with its border).
    pub fn side(&self) -> u32 {
        self.shared.side
    }

    /// R16_UNORM (16-bit archives) or R32_SFLOAT.
    pub fn unorm16(&self) -> bool {
        self.shared.unorm16
    }

    /// Is `tile` drawable from the atlas?
    pub fn holds(&self, tile: TileKey) -> bool {
        let s = self.shared.lock();
        s.layers.find(tile).is_some_and(|i| matches!(s.layers.layer(i), crate::errors::handoff::Layer::Resident { .. }))
    }

    /// The layer frame `frame` draws each of `tiles` from (recorded: the layer is kept
    /// until that frame completes), `None` for a tile not drawable; and the newest
    /// generation finished. The frame's submission waits for that generation: it is
    /// signalled already (no stall), and the wait orders the upload's writes on the
    /// errors queue before the frame's reads on the draw queue.
    pub fn draw_layers(&self, tiles: impl IntoIterator<Item = TileKey>, frame: u64) -> (Vec<Option<u32>>, u64) {
        let mut s = self.shared.lock();
        let layers = tiles.into_iter().map(|t| s.layers.draw(t, frame).map(|l| l as u32)).collect();
        (layers, s.finished)
    }

    /// The timeline the errors queue signals with each generation.
    pub fn generations(&self) -> vk::Semaphore {
        self.shared.generations.handle
    }

    /// The timeline the draw queue signals with each frame that draws from the atlas.
    pub fn frames(&self) -> vk::Semaphore {
        self.shared.frames.handle
    }

    pub fn uploaded(&self) -> Uploaded {
        self.shared.lock().uploaded
    }

    /// What the errors generations shaded so far.
    pub fn shaded(&self) -> ErrorsShaded {
        self.shared.lock().shaded.clone()
    }

    /// The largest share of wall time the errors generations may take (`--update-share`,
    /// above 0 and at most 1): after one of `u` ms the next waits `u (1 / share - 1)` ms.
    pub fn set_update_share(&self, share: f32) {
        self.shared.lock().update_share = share.clamp(f32::MIN_POSITIVE, 1.0);
    }

    /// Multiplies every block error read back from now on by `factor`: a corrupted
    /// readback, for tests that show the selection comes from these errors.
    #[doc(hidden)]
    pub fn corrupt_errors(&self, factor: f32) {
        self.shared.lock().scale_errors = factor;
    }

    /// Test hook: the errors thread fails as if the device were lost when it is about to
    /// submit block-error generation `n` (counted from 1, as [`ErrorsShaded::generations`]).
    #[doc(hidden)]
    pub fn inject_device_lost_at(&self, n: u64) {
        self.shared.lock().device_lost_at = n;
    }

    /// How the errors thread paces its generations (`--error-pacing`), on `device`'s
    /// queues: paced, each is waited for before the next is recorded; free, two may be
    /// in flight. Default: paced.
    pub fn set_pacing(&self, pacing: crate::errors::activity::Pacing, device: &Device) {
        self.shared.paced.store(pacing.paced(device.queue_mode), std::sync::atomic::Ordering::Relaxed);
        self.shared.work.notify_all();
    }

    /// The most generations the errors thread had in flight at once.
    pub fn most_in_flight(&self) -> u64 {
        self.shared.lock().most_in_flight
    }

    /// Why the errors thread stopped, if it failed: frames drawn from then on fail.
    pub fn failure(&self) -> Option<String> {
        self.shared.lock().failure.clone()
    }
}

impl Drop for HeightAtlas {
    fn drop(&mut self) {
        self.shared.lock().stop = true;
        self.shared.work.notify_all();
        if let Some(t) = self.thread.take() {
            let _ = t.join();
        }
    }
}

impl TileGate for AtlasFeed {
    fn send(&self, tiles: Vec<Read>) {
        if tiles.is_empty() {
            return;
        }
        let mut s = self.shared.lock();
        if s.stop || s.failure.is_some() {
            return; // nothing will take them: the frames fail with the reason
        }
        s.busy += tiles.len();
        s.todo.extend(tiles);
        drop(s);
        self.shared.work.notify_all();
    }

    fn take(&self) -> (Vec<Read>, Vec<TileKey>) {
        let mut s = self.shared.lock();
        (std::mem::take(&mut s.done), std::mem::take(&mut s.dropped))
    }

    fn release(&self, keys: Vec<TileKey>) {
        if !keys.is_empty() {
            self.shared.lock().released.extend(keys);
        }
    }

    fn wait(&self) {
        let mut s = self.shared.lock();
        while s.busy > 0 && s.failure.is_none() && !s.stop {
            s = self.shared.progress.wait(s).unwrap_or_else(|e| e.into_inner());
        }
    }

    fn request_errors(&self, view: View, tiles: Vec<TileKey>, height_scale: f64, mode: ErrorMode) {
        let mut s = self.shared.lock();
        if s.stop || s.failure.is_some() {
            return;
        }
        s.requested += 1;
        s.request = Some(ErrorsRequest { number: s.requested, view, tiles, height_scale, mode });
        drop(s);
        self.shared.work.notify_all();
    }

    fn errors(&self) -> Option<Arc<TileErrors>> {
        self.shared.lock().errors.clone()
    }

    fn wait_errors(&self) {
        let mut s = self.shared.lock();
        if s.answered < s.requested {
            s.hurry = true;
            self.shared.work.notify_all();
        }
        while s.answered < s.requested && s.failure.is_none() && !s.stop {
            s = self.shared.progress.wait(s).unwrap_or_else(|e| e.into_inner());
        }
    }
}

/// The layer state sampled by draws and by the errors passes (and left so by every
/// upload).
const SAMPLED: (vk::PipelineStageFlags2, vk::AccessFlags2, vk::ImageLayout) = (
    vk::PipelineStageFlags2::from_raw(
        vk::PipelineStageFlags2::VERTEX_SHADER.as_raw() | vk::PipelineStageFlags2::FRAGMENT_SHADER.as_raw(),
    ),
    vk::AccessFlags2::SHADER_SAMPLED_READ,
    vk::ImageLayout::SHADER_READ_ONLY_OPTIMAL,
);

/// The errors activity's thread for tiles: each batch of tiles handed over is uploaded
/// as one generation (layers claimed under the lock, heights and deviations copied on
/// the errors queue), then handed back once the generation has finished; each request
/// for errors is shaded as one generation over the tiles it names that are resident
/// ([`AtlasPasses`]), read back and published. Paced, each generation is waited for
/// before the next is recorded; free (`--error-pacing free`), the next is submitted
/// while the last runs, two in flight at most, each with its own command buffer,
/// staging buffer and slot of the passes (`g % 2`).
struct Activity<'a> {
    device: &'a Arc<Device>,
    shared: &'a Shared,
    trace: &'a Trace,
    cmds: [vk::CommandBuffer; 2],
    staging: [Option<Buffer>; 2],
    passes: AtlasPasses,
    /// The newest generation submitted.
    generation: u64,
    /// Generations submitted and not yet finished on this thread, oldest first.
    in_flight: std::collections::VecDeque<InFlight>,
}

/// A generation submitted: what finishing it hands over.
struct InFlight {
    g: u64,
    started: Instant,
    work: Work,
}

enum Work {
    /// Tiles uploaded (each with its layer and slot of deviations), the tiles handed back
    /// with them (`count` in all) and those that found no layer.
    Upload { count: usize, placed: Vec<Placed>, back: Vec<Read>, dropped: Vec<TileKey> },
    /// Block errors shaded for `request` over `tiles` (key, layer, slot), for the camera
    /// whose kappa is `kappa`, heights scaled as in `grid`.
    Shade { request: ErrorsRequest, tiles: Vec<(TileKey, u32, u32)>, grid: Grid, kappa: f32 },
}

/// The thread's loop: uploads first (the traversal waits for its tiles), then errors.
fn run(device: &Arc<Device>, shared: &Shared, trace: &Trace) -> VkResult<()> {
    let pool = CommandPool::new(device, device.errors_queue.family)?;
    let passes = AtlasPasses::new(device, &shared.grid, &shared.image, &shared.deviation)?;
    let cmds = [pool.allocate()?, pool.allocate()?];
    let mut a = Activity {
        device,
        shared,
        trace,
        cmds,
        staging: [None, None],
        passes,
        generation: 0,
        in_flight: Default::default(),
    };
    let result = loop {
        let (batch, request) = {
            let mut s = shared.lock();
            // A request is due once the share of wall time the errors may take allows it
            // (at once when a settle waits for it); tiles to upload are always due.
            let due =
                |s: &State| s.request.is_some() && (s.hurry || s.next_errors_at.is_none_or(|t| Instant::now() >= t));
            // With a generation in flight, nothing new to do means finishing it.
            while s.todo.is_empty() && !due(&s) && !s.stop && a.in_flight.is_empty() {
                s = match s.next_errors_at.filter(|_| s.request.is_some()) {
                    Some(t) => {
                        let wait = t.saturating_duration_since(Instant::now());
                        shared.work.wait_timeout(s, wait).unwrap_or_else(|e| e.into_inner()).0
                    }
                    None => shared.work.wait(s).unwrap_or_else(|e| e.into_inner()),
                };
            }
            if s.stop {
                break Ok(());
            }
            let request = if due(&s) { s.request.take() } else { None };
            (std::mem::take(&mut s.todo), request)
        };
        if batch.is_empty() && request.is_none() {
            // GPU work in flight and nothing new. Paced, nothing may start before it
            // finishes. Free, wait for it at most `HOST_LOOK_NS`, then look for host work
            // again (a request that can start a second generation), as the in-memory
            // errors thread does.
            let done = match a.in_flight.front() {
                Some(f) if !a.paced() => shared.generations.wait(f.g, HOST_LOOK_NS),
                _ => Ok(true),
            };
            if let Err(e) = done.and_then(|done| if done { a.finish_oldest() } else { Ok(()) }) {
                break Err(e);
            }
            continue;
        }
        if !batch.is_empty() {
            if let Err(e) = a.upload_batch(batch) {
                break Err(e);
            }
        }
        if let Some(request) = request {
            if let Err(e) = a.shade(request) {
                break Err(e);
            }
        }
    };
    // Every generation submitted is waited for before the pool and staging go (a lost
    // device answers at once).
    let last = a.generation;
    let _ = shared.generations.wait(last, u64::MAX);
    a.cmds.into_iter().for_each(|cmd| pool.free(cmd));
    result
}

impl Activity<'_> {
    /// Whether each generation is waited for before the next is recorded.
    fn paced(&self) -> bool {
        self.shared.paced.load(std::sync::atomic::Ordering::Relaxed)
    }

    /// Makes room for generation `self.generation + 1`: at most one other in flight (its
    /// command buffer, staging and slot are the other ones).
    fn make_room(&mut self) -> VkResult<()> {
        while self.in_flight.len() >= 2 {
            self.finish_oldest()?;
        }
        Ok(())
    }

    /// Submits `cmd` (recorded) as generation `g` on the errors queue, to be finished
    /// with `work`; paced, finishes it at once.
    fn submit(&mut self, g: u64, started: Instant, work: Work) -> VkResult<()> {
        let shared = self.shared;
        let cmd = self.cmds[Handoff::slot(g)];
        let cmds = [vk::CommandBufferSubmitInfo::default().command_buffer(cmd)];
        let signal = [vk::SemaphoreSubmitInfo::default()
            .semaphore(shared.generations.handle)
            .value(g)
            .stage_mask(vk::PipelineStageFlags2::ALL_COMMANDS)];
        let submit = vk::SubmitInfo2::default().command_buffer_infos(&cmds).signal_semaphore_infos(&signal);
        self.device.errors_queue.submit(self.device, &[submit], vk::Fence::null())?;
        self.generation = g;
        self.in_flight.push_back(InFlight { g, started, work });
        {
            let mut s = shared.lock();
            s.most_in_flight = s.most_in_flight.max(self.in_flight.len() as u64);
        }
        if self.paced() {
            self.finish_oldest()?;
        }
        Ok(())
    }

    /// Waits for the oldest generation in flight and hands over what it did.
    fn finish_oldest(&mut self) -> VkResult<()> {
        let Some(InFlight { g, started, work }) = self.in_flight.pop_front() else { return Ok(()) };
        self.shared.generations.wait(g, u64::MAX)?;
        match work {
            Work::Upload { count, placed, back, dropped } => {
                self.uploaded(Some(g), started, count, (placed, back, dropped));
                Ok(())
            }
            Work::Shade { request, tiles, grid, kappa } => self.shaded(g, started, request, (tiles, grid, kappa)),
        }
    }

    /// Places, uploads and (once its generation has finished) hands back one batch of
    /// tiles read.
    fn upload_batch(&mut self, batch: Vec<Read>) -> VkResult<()> {
        let shared = self.shared;
        let count = batch.len();
        let started = Instant::now();
        self.make_room()?;
        let g = self.generation + 1;
        // Frames that drew from a layer must have completed before it is rewritten: the
        // draw queue's timeline, read now (a stale value only protects more). Errors
        // generations still in flight keep the layers they read ([`AtlasLayers::claim`]).
        let completed = shared.frames.value()?;
        let (mut back, mut placed, mut dropped) = (Vec::new(), Vec::new(), Vec::new());
        {
            let mut s = shared.lock();
            let State { layers, released, slots, .. } = &mut *s;
            for (tile, bytes) in batch {
                let key = tile.key;
                if layers.find(key).is_some() {
                    // Let go by the cache and read again: its layer still holds it.
                    released.remove(&key);
                    back.push((tile, bytes));
                } else if let Some(layer) = layers.claim(key, g, completed, |t| !released.contains(&t)) {
                    // Let go once, read again into another layer: held from now on.
                    released.remove(&key);
                    // The errors passes that read the layer's old deviations have finished.
                    let slot = slots.place(layer, key.level > 0);
                    placed.push((tile.clone(), layer, slot));
                    back.push((tile, bytes));
                } else {
                    dropped.push(key);
                }
            }
            if released.len() > 2 * MAX_LAYERS as usize {
                released.retain(|k| layers.find(*k).is_some());
            }
        }
        if placed.is_empty() {
            // Nothing to upload: handed back after the generations before it, in order.
            while !self.in_flight.is_empty() {
                self.finish_oldest()?;
            }
            self.uploaded(None, started, count, (placed, back, dropped));
            return Ok(());
        }
        let layer_bytes = HeightAtlas::staged_bytes(&shared.grid);
        let need = (layer_bytes * placed.len()) as u64;
        let staging = &mut self.staging[Handoff::slot(g)];
        if staging.as_ref().is_none_or(|b| b.size < need) {
            drop(staging.take()); // the old one first: its generation has finished
            *staging = Some(Buffer::new(
                self.device,
                "atlas staging",
                need,
                vk::BufferUsageFlags::TRANSFER_SRC,
                gpu_allocator::MemoryLocation::CpuToGpu,
            )?);
        }
        let staging = staging.as_mut().expect("made above");
        upload(self.device, shared, self.cmds[Handoff::slot(g)], staging, &placed)?;
        self.submit(g, started, Work::Upload { count, placed, back, dropped })
    }

    /// Hands over a batch of `count` tiles: those uploaded as generation `g` (finished)
    /// into their layers, and those handed back or dropped with them.
    fn uploaded(
        &self,
        g: Option<u64>,
        started: Instant,
        count: usize,
        (placed, back, dropped): (Vec<Placed>, Vec<Read>, Vec<TileKey>),
    ) {
        let shared = self.shared;
        // Outside the state's lock: the trace has its own.
        let args = serde_json::json!({"generation": g.unwrap_or(self.generation), "tiles": count,
            "uploaded": placed.len(), "without_a_layer": dropped.len()});
        let name = if placed.is_empty() { "tiles back (none to upload)" } else { "upload tiles" };
        self.trace.complete(ERRORS_TID, name, started, Instant::now(), args);
        {
            let mut s = shared.lock();
            if let Some(g) = g {
                s.layers.finish(g);
                s.finished = g;
                s.uploaded.generations += 1;
                s.uploaded.tiles += placed.len() as u64;
                let (h, d) =
                    (HeightAtlas::height_layer_bytes(&shared.grid), HeightAtlas::deviation_slot_bytes(&shared.grid));
                s.uploaded.bytes += placed.iter().map(|(_, _, slot)| h + slot.map_or(0, |_| d)).sum::<u64>();
            }
            s.uploaded.dropped += dropped.len() as u64;
            s.done.extend(back);
            s.dropped.extend(dropped);
            s.busy = s.busy.saturating_sub(count);
        }
        shared.progress.notify_all();
    }

    /// Shades the block errors `request` asks for as one generation, over the tiles it
    /// names that are resident and not let go (their layers are kept until this
    /// generation has finished: [`AtlasLayers::read_for_errors`]), and publishes them
    /// once it has.
    fn shade(&mut self, request: ErrorsRequest) -> VkResult<()> {
        let shared = self.shared;
        // The terrain's heights as the traversal scales them now.
        let grid = Grid { height_scale: request.height_scale, ..shared.grid };
        let started = Instant::now();
        let paper = request.mode == ErrorMode::Paper;
        self.make_room()?;
        let g = self.generation + 1;
        let tiles: Vec<(TileKey, u32, u32)> = {
            let mut s = shared.lock();
            let resident = |k: &TileKey| {
                let i = s.layers.find(*k)?;
                let held = matches!(s.layers.layer(i), crate::errors::handoff::Layer::Resident { .. });
                // Strict mode reads the tile's D; the paper's only its heights.
                let slot = if paper { s.slots.of(i).unwrap_or(0) } else { s.slots.of(i)? };
                (held && !s.released.contains(k)).then_some((*k, i as u32, slot))
            };
            // Strict: tiles with a D (above level 0). Paper: every tile (it gives the blocks
            // one LOD above its own: a tile holds at least two a side, `Grid::with_block`).
            let shaded = |k: &&TileKey| paper || k.level > 0;
            let tiles: Vec<_> =
                request.tiles.iter().filter(shaded).filter_map(resident).take(AtlasPasses::capacity()).collect();
            for &(_, layer, _) in &tiles {
                s.layers.read_for_errors(layer as usize, g);
            }
            tiles
        };
        if tiles.is_empty() {
            self.answered(request.number, started);
            return Ok(());
        }
        let nth = {
            let s = shared.lock();
            (s.shaded.generations + self.shading_in_flight() + 1, s.device_lost_at)
        };
        if nth.0 == nth.1 {
            let lost = Err::<(), _>(vk::Result::ERROR_DEVICE_LOST).vk("vkQueueSubmit2 (injected fault)");
            return lost.map_err(|e| VkError::Thread { stage: format!("generation {}", nth.0), cause: Box::new(e) });
        }
        let (anchor, cam) = request.view.relative(&grid);
        let d = &self.device.raw;
        let cmd = self.cmds[Handoff::slot(g)];
        // SAFETY: `cmd` belongs to this thread's pool and its last submission (generation
        // `g - 2`) has finished (begin resets it).
        unsafe { crate::vk::begin_one_time(d, cmd)? };
        self.passes.record(g, cmd, &grid, &tiles, (anchor, &cam), (shared.unorm16, request.mode));
        // SAFETY: recording, as above.
        unsafe { d.end_command_buffer(cmd).vk("vkEndCommandBuffer")? };
        let kappa = cam.kappa();
        self.submit(g, started, Work::Shade { request, tiles, grid, kappa })
    }

    /// Errors generations in flight.
    fn shading_in_flight(&self) -> u64 {
        self.in_flight.iter().filter(|f| matches!(f.work, Work::Shade { .. })).count() as u64
    }

    /// Reads back errors generation `g` (finished) and publishes it.
    fn shaded(
        &self,
        g: u64,
        started: Instant,
        request: ErrorsRequest,
        (tiles, grid, kappa): (Vec<(TileKey, u32, u32)>, Grid, f32),
    ) -> VkResult<()> {
        let shared = self.shared;
        let (blocks, shaded) = self.passes.read(g, &grid, &tiles, request.mode)?;
        let scale = shared.lock().scale_errors;
        let tiles: foldhash::HashMap<TileKey, Vec<f32>> =
            blocks.into_iter().map(|(k, b)| (k, b.into_iter().map(|e| e * scale).collect())).collect();
        let paper = match request.mode {
            ErrorMode::Paper => {
                use crate::stream::errors::{nested_paper_errors, paper_own_errors};
                let n = grid.tile_quads / grid.block_quads;
                let own = tiles.iter().flat_map(|(&k, cell)| paper_own_errors(k, cell, n, grid.top)).collect();
                nested_paper_errors(&own)
            }
            ErrorMode::Strict => Default::default(),
        };
        // Strict mode's per-tile blocks; the paper's are in `paper`.
        let tiles = if request.mode == ErrorMode::Strict { tiles } else { Default::default() };
        let errors = TileErrors {
            generation: g,
            position: request.view.position,
            kappa,
            height_scale: grid.height_scale,
            gpu_ms: shaded.gpu_ms,
            tiles,
            mode: request.mode,
            paper,
        };
        {
            let mut s = shared.lock();
            s.layers.finish(g);
            s.finished = g;
            s.errors = Some(Arc::new(errors));
            s.shaded.add(&shaded);
        }
        let args = serde_json::json!({"generation": g, "tiles": shaded.tiles, "groups": shaded.groups,
            "bytes_read_back": shaded.bytes_read_back, "gpu_ms": shaded.gpu_ms});
        self.trace.complete(ERRORS_TID, "block errors", started, Instant::now(), args);
        self.answered(request.number, started);
        Ok(())
    }

    /// Request `number` is answered (shaded, or found nothing to shade): a settle waiting
    /// for it goes on, and the next waits as the share of wall time asks.
    fn answered(&self, number: u64, started: Instant) {
        let mut s = self.shared.lock();
        s.answered = s.answered.max(number);
        s.hurry &= s.answered < s.requested;
        // After an update of u, the next waits u (1 / share - 1): the errors take at most
        // `share` of the wall time. (At most a day: longer is never, and an Instant
        // cannot overflow.)
        let wait = started.elapsed().as_secs_f64() * (1.0 / f64::from(s.update_share) - 1.0);
        s.next_errors_at = Some(Instant::now() + std::time::Duration::from_secs_f64(wait.min(86_400.0)));
        drop(s);
        self.shared.progress.notify_all();
    }
}

/// Records into `cmd` the copy of `placed` tiles (heights, and the deviations of tiles
/// above level 0) into their layers.
fn upload(
    device: &Arc<Device>,
    shared: &Shared,
    cmd: vk::CommandBuffer,
    staging: &mut Buffer,
    placed: &[Placed],
) -> VkResult<()> {
    let height_bytes = (shared.side * shared.side) as usize * shared.grid.atlas_texel_bytes();
    let groups = shared.grid.tile_quads as u32;
    let layer_bytes = HeightAtlas::staged_bytes(&shared.grid);
    let layer_of = |base_array_layer: u32| vk::ImageSubresourceLayers {
        aspect_mask: vk::ImageAspectFlags::COLOR,
        mip_level: 0,
        base_array_layer,
        layer_count: 1,
    };
    let (mut heights, mut deviations) = (Vec::with_capacity(placed.len()), Vec::new());
    {
        let dst = staging.mapped_mut()?;
        for (i, (tile, layer, slot)) in placed.iter().enumerate() {
            let at = &mut dst[i * layer_bytes..][..layer_bytes];
            let (h, dev) = at.split_at_mut(height_bytes);
            let voids = shared.grid.holes.then_some(tile.voids.as_deref());
            texels(&tile.heights, voids, shared.unorm16, h)
                .map_err(|e| VkError::Setup(format!("tile {:?}: {e}", tile.key)))?;
            heights.push(
                vk::BufferImageCopy::default()
                    .buffer_offset((i * layer_bytes) as u64)
                    .image_subresource(layer_of(*layer as u32))
                    .image_extent(vk::Extent3D { width: shared.side, height: shared.side, depth: 1 }),
            );
            if let Some(slot) = slot {
                deviation_texels(&tile.deviation[..(groups * groups) as usize], dev);
                deviations.push(
                    vk::BufferImageCopy::default()
                        .buffer_offset((i * layer_bytes + height_bytes) as u64)
                        .image_subresource(layer_of(*slot))
                        .image_extent(vk::Extent3D { width: groups, height: groups, depth: 1 }),
                );
            }
        }
    }
    let d = &device.raw;
    // The layer's old tile is discarded: the frames that drew it have completed (their
    // timeline value was read before the layer was claimed). The errors passes that read
    // it ran earlier on this queue, so the barrier's first scope (fragment shaders
    // included) waits for them; `AtlasLayers::claim` also keeps a layer an unfinished
    // generation reads, so the rule holds whichever queue writes the layer.
    let reused = (SAMPLED.0, vk::AccessFlags2::NONE, vk::ImageLayout::UNDEFINED);
    let written =
        (vk::PipelineStageFlags2::COPY, vk::AccessFlags2::TRANSFER_WRITE, vk::ImageLayout::TRANSFER_DST_OPTIMAL);
    // SAFETY: `cmd` belongs to this thread's pool and its last submission (generation
    // `g - 2`) has finished (begin resets it); staging and images outlive the
    // generation (finished before the staging is reused or the thread ends); every
    // region lies inside its layer.
    unsafe {
        crate::vk::begin_one_time(d, cmd)?;
        for (image, layer) in written_layers(shared, placed) {
            let range = vk::ImageSubresourceRange { base_array_layer: layer, layer_count: 1, ..image.range(0, 1) };
            image_barrier(d, cmd, image.handle, range, reused, written);
        }
        let dst = vk::ImageLayout::TRANSFER_DST_OPTIMAL;
        d.cmd_copy_buffer_to_image(cmd, staging.handle, shared.image.handle, dst, &heights);
        if !deviations.is_empty() {
            d.cmd_copy_buffer_to_image(cmd, staging.handle, shared.deviation.handle, dst, &deviations);
        }
        for (image, layer) in written_layers(shared, placed) {
            let range = vk::ImageSubresourceRange { base_array_layer: layer, layer_count: 1, ..image.range(0, 1) };
            image_barrier(d, cmd, image.handle, range, written, SAMPLED);
        }
        d.end_command_buffer(cmd).vk("vkEndCommandBuffer")?;
    }
    Ok(())
}

/// The layers an upload of `placed` writes: each tile's layer of heights and its slot
/// of deviations, if it has one.
fn written_layers<'a>(shared: &'a Shared, placed: &'a [Placed]) -> impl Iterator<Item = (&'a Image, u32)> + 'a {
    placed.iter().flat_map(move |(_, layer, slot)| {
        std::iter::once((&shared.image, *layer as u32)).chain(slot.map(|s| (&shared.deviation, s)))
    })
}

/// A tile's group deviations as the atlas's R16_SFLOAT texels, each rounded up (the
/// nearest half-float at or above it): a bound from them is never below the exact one.
fn deviation_texels(d: &[f32], dst: &mut [u8]) {
    for (i, &v) in d.iter().enumerate() {
        dst[2 * i..2 * i + 2].copy_from_slice(&f16_at_or_above(v).to_ne_bytes());
    }
}

/// The bits of the least half-float at or above `v` (`v >= 0`; NaN and values past
/// 65504 give infinity, which bounds nothing: the tile's own bound is used instead).
pub fn f16_at_or_above(v: f32) -> u16 {
    if v.is_nan() || v > 65504.0 {
        return 0x7c00;
    }
    if v <= 0.0 {
        return 0;
    }
    const SUBNORMAL_STEP: f32 = 1.0 / 16_777_216.0; // 2^-24
    if v < 6.103_515_6e-5 {
        // Subnormal: multiples of 2^-24 (exact in f32); 1024 steps is the least normal.
        return (v / SUBNORMAL_STEP).ceil() as u16;
    }
    let bits = v.to_bits();
    let exp = ((bits >> 23) & 0xff) as i32 - 127 + 15;
    let mant = bits & 0x7f_ffff;
    let h = ((exp as u32) << 10 | mant >> 13) as u16;
    // Dropped bits: one step up (a carry into the exponent is the next binade, or
    // infinity past 65504).
    if mant & 0x1fff != 0 {
        h + 1
    } else {
        h
    }
}

/// The value of half-float bits `h` (for checks).
pub fn f16_value(h: u16) -> f32 {
    let (exp, mant) = (i32::from((h >> 10) & 0x1f), f32::from(h & 0x3ff));
    match exp {
        0 => mant / 16_777_216.0,
        31 => f32::INFINITY,
        e => (1.0 + mant / 1024.0) * 2f32.powi(e - 15),
    }
}

/// A tile's heights as the atlas's texels: 16-bit integers for R16_UNORM (exact: the
/// shader rounds `texel * 65535` back), f32 otherwise. With `voids` (an atlas with
/// holes; `Some(None)` for a tile without any), each height is followed by 1 (65535 in
/// 16 bits) where it is a void, else 0.
pub fn texels(heights: &Heights, voids: Option<Option<&[bool]>>, unorm16: bool, dst: &mut [u8]) -> Result<(), String> {
    let width = if unorm16 { 2 } else { 4 };
    let channels = if voids.is_some() { 2 } else { 1 };
    let n = dst.len() / (width * channels);
    let count = match heights {
        Heights::Unorm16(v) => v.len(),
        Heights::Float32(v) => v.len(),
    };
    if count != n || voids.flatten().is_some_and(|v| v.len() != n) {
        return Err(format!("{count} heights for a layer of {n}"));
    }
    for i in 0..n {
        let h = heights.get(i);
        let at = &mut dst[i * width * channels..][..width * channels];
        if unorm16 && (h.fract() != 0.0 || !(0.0..=65535.0).contains(&h)) {
            return Err(format!("height {h} in a 16-bit archive"));
        }
        let void = voids.map(|v| v.is_some_and(|v| v[i]));
        for (c, value) in std::iter::once(h).chain(void.map(|v| if v { 1.0 } else { 0.0 })).enumerate() {
            let texel = &mut at[c * width..][..width];
            if unorm16 {
                // A void's 1.0 is 65535 in the second channel.
                let units = if c == 0 { value } else { value * 65535.0 };
                texel.copy_from_slice(&(units as u16).to_ne_bytes());
            } else {
                texel.copy_from_slice(&value.to_ne_bytes());
            }
        }
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Under random placements: no two layers ever hold one slot, every slot is held or
    /// free (never both, never lost), a tile that wants one gets one whenever one is free,
    /// and one that does not gets none.
    /// The default budget holds every tile of the largest terrain whose tiles fit the
    /// layers (f32 8193^2, 16-bit and with holes alike), not one layer short, and a small
    /// terrain's about as many layers as it has tiles; a terrain with more tiles gets the
    /// fixed default.
    #[test]
    fn the_default_budget_holds_every_tile_when_they_fit_the_layers() {
        let grid = |side: usize, height_bytes: usize, holes: bool| Grid {
            width: side,
            height: side,
            tile_quads: 256,
            top: ((side - 1) / 256).trailing_zeros() as u8,
            spacing: [1.0, 1.0],
            height_scale: 1.0,
            origin: [0.0, 0.0],
            height_bytes,
            block_quads: 32,
            holes,
        };
        for (side, bytes, holes, tiles) in [
            (8193, 4, false, 1365),
            (8193, 2, false, 1365),
            (8193, 4, true, 1365),
            (1025, 2, false, 21),
            (257, 2, false, 1),
        ] {
            let g = grid(side, bytes, holes);
            let mb = HeightAtlas::default_budget_mb(&g);
            let layers = HeightAtlas::layers_for(&g, u64::from(mb) << 20, MAX_LAYERS);
            let held = HeightAtlas::cache_tiles(layers);
            assert!(held >= tiles, "{side}^2 x {bytes} bytes, holes {holes}: {mb} MB hold {held} of {tiles} tiles");
            // And not a megabyte more than that.
            let fewer = HeightAtlas::layers_for(&g, u64::from(mb - 1) << 20, MAX_LAYERS);
            assert!(
                mb == 1 || HeightAtlas::cache_tiles(fewer) < tiles,
                "{side}^2: {mb} MB is more than the tiles need"
            );
        }
        // 16385^2: 5,461 tiles, more than the layers.
        assert_eq!(HeightAtlas::default_budget_mb(&grid(16385, 4, false)), DEFAULT_BUDGET_MB);
    }

    #[test]
    fn a_deviation_slot_is_held_by_one_layer_at_a_time_and_never_lost() {
        let (layers, slots) = (12usize, 5u32);
        let mut d = DeviationSlots::new(layers, slots);
        let mut state = 0x9e37_79b9_7f4a_7c15u64;
        let mut next = |n: u64| {
            state ^= state << 13;
            state ^= state >> 7;
            state ^= state << 17;
            state % n
        };
        let (mut granted, mut refused) = (0, 0);
        for _ in 0..20_000 {
            let (layer, wants) = (next(layers as u64) as usize, next(3) > 0);
            let free_before = d.free.len() + usize::from(d.of(layer).is_some());
            let got = d.place(layer, wants);
            assert_eq!(got.is_some(), wants && free_before > 0, "{d:?}");
            granted += usize::from(got.is_some());
            refused += usize::from(wants && got.is_none());
            let mut held: Vec<u32> = d.of_layer.iter().flatten().copied().collect();
            held.extend(&d.free);
            held.sort();
            assert_eq!(held, (0..slots).collect::<Vec<_>>(), "a slot held twice or lost: {d:?}");
        }
        assert!(granted > 1000 && refused > 100, "{granted} granted, {refused} refused");
    }

    /// With holes each height is followed by its void flag (1.0, or 65535 in 16 bits); a
    /// tile without a mask writes 0 there; a mask of the wrong size is refused.
    #[test]
    fn texels_with_holes_interleave_heights_and_void_flags() {
        let heights = Heights::Unorm16(vec![7, 65535, 0]);
        let mut dst = [0u8; 12];
        texels(&heights, Some(Some(&[false, true, false])), true, &mut dst).unwrap();
        let words: Vec<u16> = dst.chunks(2).map(|c| u16::from_ne_bytes([c[0], c[1]])).collect();
        assert_eq!(words, [7, 0, 65535, 65535, 0, 0]);
        texels(&heights, Some(None), true, &mut dst).unwrap();
        let words: Vec<u16> = dst.chunks(2).map(|c| u16::from_ne_bytes([c[0], c[1]])).collect();
        assert_eq!(words, [7, 0, 65535, 0, 0, 0]);
        let floats = Heights::Float32(vec![-2.5, 1e6]);
        let mut dst = [0u8; 16];
        texels(&floats, Some(Some(&[true, false])), false, &mut dst).unwrap();
        let values: Vec<f32> = dst.chunks(4).map(|c| f32::from_ne_bytes(c.try_into().unwrap())).collect();
        assert_eq!(values, [-2.5, 1.0, 1e6, 0.0]);
        assert!(texels(&floats, Some(Some(&[true])), false, &mut dst).is_err());
        let mut plain = [0u8; 8];
        texels(&floats, None, false, &mut plain).unwrap();
        assert_eq!(f32::from_ne_bytes(plain[4..].try_into().unwrap()), 1e6);
    }

    /// The half float stored for a deviation is never below it and is the least such:
    /// the one below it (where there is one) is below the value. Across the normal and
    /// subnormal ranges, exact values, and past the largest half float.
    #[test]
    fn deviations_round_up_to_the_least_half_float_at_or_above() {
        let mut v = 1e-9f32;
        let mut checked = 0;
        while v < 1e6 {
            for x in [v, v * 1.000_01, f32::from_bits(v.to_bits() + 1)] {
                let h = f16_at_or_above(x);
                let up = f16_value(h);
                assert!(up >= x, "{x}: {up}");
                if h > 0 && up.is_finite() {
                    assert!(f16_value(h - 1) < x, "{x}: {} is at or above it too", f16_value(h - 1));
                }
                checked += 1;
            }
            v *= 1.37;
        }
        assert!(checked > 150);
        for exact in [0.0f32, 1.0, 0.5, 1024.0, 65504.0, 6.103_515_6e-5, 5.960_464_5e-8] {
            assert_eq!(f16_value(f16_at_or_above(exact)), exact);
        }
        assert_eq!(f16_at_or_above(65505.0), 0x7c00);
        assert_eq!(f16_at_or_above(f32::NAN), 0x7c00);
    }
}
