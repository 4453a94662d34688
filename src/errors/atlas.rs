//! The heightfield atlas of streamed frames and the errors activity that fills it (SPEC
//! section 8, "Residency" and "Budgets"): one array image, a tile's heights (its
//! one-sample border included) in each layer. Tiles the IO thread read are handed to the
//! errors activity's thread ([`AtlasFeed`], the streamer's end), which uploads them on
//! the errors queue, one generation a batch, and hands them back once the generation has
//! finished: only then does the host cache take them, so the traversal selects only tiles
//! the draw thread can draw. Layers are handed out and reused under [`AtlasLayers`]'
//! rules: a layer is rewritten only once every frame that drew from it has completed (the
//! draw queue's timeline, read, never waited on) and the host cache has let its tile go.
//! Streamed tiles bring their block errors from the archive (computed by `prepare`), so
//! a generation's GPU work is the copy alone.

use crate::errors::handoff::AtlasLayers;
use crate::stream::cache::{Heights, TileData};
use crate::stream::streamer::TileGate;
use crate::stream::{Grid, TileKey};
use crate::trace::{Trace, ERRORS_TID};
use crate::vk::{
    image_barrier, vk, Buffer, CommandPool, Device, Image, TimelineSemaphore, VkError, VkResult, VkResultExt,
};
use std::collections::HashSet;
use std::sync::{Arc, Condvar, Mutex};
use std::thread::JoinHandle;

/// The most layers an atlas takes, whatever the budget (llvmpipe's limit).
pub const MAX_LAYERS: u32 = 2048;

/// A tile read by the IO thread and the bytes read for it.
pub type Read = (Arc<TileData>, u64);

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
    /// Declared first: dropped after the thread that writes it has been joined.
    image: Image,
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
    /// Bytes of one layer: a tile with its one-sample border.
    pub fn layer_bytes(grid: &Grid) -> u64 {
        let side = (grid.tile_quads + 3) as u64;
        side * side * grid.height_bytes as u64
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
        let format = if unorm16 { vk::Format::R16_UNORM } else { vk::Format::R32_SFLOAT };
        let usage =
            vk::ImageUsageFlags::SAMPLED | vk::ImageUsageFlags::TRANSFER_DST | vk::ImageUsageFlags::TRANSFER_SRC;
        let extent = vk::Extent2D { width: side, height: side };
        // Shared: written on the errors queue, sampled on the draw queue.
        let image = Image::array(device, "heightfield atlas", extent, format, layers, usage, true)?;
        {
            // Every layer starts readable (a draw's descriptor covers all of them), before
            // either activity uses the image.
            let pool = CommandPool::new(device, device.draw_queue.family)?;
            let range = image.range(0, 1);
            device.one_shot(&pool, |cmd| {
                let undefined = (vk::PipelineStageFlags2::NONE, vk::AccessFlags2::NONE, vk::ImageLayout::UNDEFINED);
                // SAFETY: `cmd` is recording; the image outlives one_shot's wait.
                unsafe { image_barrier(&device.raw, cmd, image.handle, range, undefined, SAMPLED) };
            })?;
        }
        let shared = Arc::new(Shared {
            image,
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
            }),
            work: Condvar::new(),
            progress: Condvar::new(),
            generations: TimelineSemaphore::new(device, 0)?,
            frames: TimelineSemaphore::new(device, 0)?,
        });
        let thread = std::thread::Builder::new()
            .name("vkterrain-atlas".into())
            .spawn({
                let (device, shared) = (device.clone(), shared.clone());
                move || {
                    if let Err(e) = uploads(&device, &shared, &trace) {
                        let mut s = shared.lock();
                        s.failure = Some(format!("atlas uploads: {e}"));
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
}

/// The layer state sampled by draws (and left so by every upload).
const SAMPLED: (vk::PipelineStageFlags2, vk::AccessFlags2, vk::ImageLayout) = (
    vk::PipelineStageFlags2::VERTEX_SHADER,
    vk::AccessFlags2::SHADER_SAMPLED_READ,
    vk::ImageLayout::SHADER_READ_ONLY_OPTIMAL,
);

/// The errors activity's loop for a streamed terrain: each batch of tiles handed over is
/// one generation (layers claimed under the lock, the heights copied on the errors queue,
/// the generation's timeline value waited for on this thread), then handed back.
fn uploads(device: &Arc<Device>, shared: &Shared, trace: &Trace) -> VkResult<()> {
    let pool = CommandPool::new(device, device.errors_queue.family)?;
    let cmd = pool.allocate()?;
    let texel = if shared.unorm16 { 2 } else { 4 };
    let layer_bytes = (shared.side * shared.side) as usize * texel;
    let mut staging: Option<Buffer> = None;
    let mut generation = 0u64;
    let result = loop {
        let batch = {
            let mut s = shared.lock();
            while s.todo.is_empty() && !s.stop {
                s = shared.work.wait(s).unwrap_or_else(|e| e.into_inner());
            }
            if s.stop {
                break Ok(());
            }
            std::mem::take(&mut s.todo)
        };
        let count = batch.len();
        let started = std::time::Instant::now();
        let g = generation + 1;
        // Frames that drew from a layer must have completed before it is rewritten: the
        // draw queue's timeline, read now (a stale value only protects more).
        let completed = match shared.frames.value() {
            Ok(v) => v,
            Err(e) => break Err(e),
        };
        let (mut back, mut placed, mut dropped) = (Vec::new(), Vec::new(), Vec::new());
        {
            let mut s = shared.lock();
            let State { layers, released, .. } = &mut *s;
            for (tile, bytes) in batch {
                let key = tile.key;
                if layers.find(key).is_some() {
                    // Let go by the cache and read again: its layer still holds it.
                    released.remove(&key);
                    back.push((tile, bytes));
                } else if let Some(layer) = layers.claim(key, g, completed, |t| !released.contains(&t)) {
                    // Let go once, read again into another layer: held from now on.
                    released.remove(&key);
                    placed.push((tile.clone(), layer));
                    back.push((tile, bytes));
                } else {
                    dropped.push(key);
                }
            }
            if released.len() > 2 * MAX_LAYERS as usize {
                released.retain(|k| layers.find(*k).is_some());
            }
        }
        if !placed.is_empty() {
            let need = (layer_bytes * placed.len()) as u64;
            if staging.as_ref().is_none_or(|b| b.size < need) {
                drop(staging.take()); // the old one first: it was waited for
                staging = Some(Buffer::new(
                    device,
                    "atlas staging",
                    need,
                    vk::BufferUsageFlags::TRANSFER_SRC,
                    gpu_allocator::MemoryLocation::CpuToGpu,
                )?);
            }
            let staging = staging.as_mut().expect("made above");
            if let Err(e) = upload(device, shared, cmd, staging, &placed, layer_bytes, g) {
                break Err(e);
            }
            generation = g;
        }
        // Outside the state's lock: the trace has its own.
        let args = serde_json::json!({"generation": g, "tiles": count, "uploaded": placed.len(), "without_a_layer": dropped.len()});
        let name = if placed.is_empty() { "tiles back (none to upload)" } else { "upload tiles" };
        trace.complete(ERRORS_TID, name, started, std::time::Instant::now(), args);
        {
            let mut s = shared.lock();
            if !placed.is_empty() {
                s.layers.finish(g);
                s.finished = g;
                s.uploaded.generations += 1;
                s.uploaded.tiles += placed.len() as u64;
                s.uploaded.bytes += (layer_bytes * placed.len()) as u64;
            }
            s.uploaded.dropped += dropped.len() as u64;
            s.done.extend(back);
            s.dropped.extend(dropped);
            s.busy = s.busy.saturating_sub(count);
        }
        shared.progress.notify_all();
    };
    // The last generation was waited for: the pool and staging may go.
    pool.free(cmd);
    result
}

/// Copies `placed` tiles into their layers as generation `g` on the errors queue, and
/// waits for the generation on this thread.
fn upload(
    device: &Arc<Device>,
    shared: &Shared,
    cmd: vk::CommandBuffer,
    staging: &mut Buffer,
    placed: &[(Arc<TileData>, usize)],
    layer_bytes: usize,
    g: u64,
) -> VkResult<()> {
    let mut regions = Vec::with_capacity(placed.len());
    {
        let dst = staging.mapped_mut()?;
        for (i, (tile, layer)) in placed.iter().enumerate() {
            texels(&tile.heights, shared.unorm16, &mut dst[i * layer_bytes..][..layer_bytes])
                .map_err(|e| VkError::Setup(format!("tile {:?}: {e}", tile.key)))?;
            regions.push(
                vk::BufferImageCopy::default()
                    .buffer_offset((i * layer_bytes) as u64)
                    .image_subresource(vk::ImageSubresourceLayers {
                        aspect_mask: vk::ImageAspectFlags::COLOR,
                        mip_level: 0,
                        base_array_layer: *layer as u32,
                        layer_count: 1,
                    })
                    .image_extent(vk::Extent3D { width: shared.side, height: shared.side, depth: 1 }),
            );
        }
    }
    let image = &shared.image;
    let d = &device.raw;
    // The layer's old tile is discarded: the frames that drew it have completed (their
    // timeline value was read before the layer was claimed).
    let reused = (vk::PipelineStageFlags2::VERTEX_SHADER, vk::AccessFlags2::NONE, vk::ImageLayout::UNDEFINED);
    let written =
        (vk::PipelineStageFlags2::COPY, vk::AccessFlags2::TRANSFER_WRITE, vk::ImageLayout::TRANSFER_DST_OPTIMAL);
    // SAFETY: `cmd` belongs to this thread's pool and its last submission was waited for
    // (begin resets it); staging and image outlive the wait below; every region lies
    // inside its layer.
    unsafe {
        crate::vk::begin_one_time(d, cmd)?;
        for (_, layer) in placed {
            let range =
                vk::ImageSubresourceRange { base_array_layer: *layer as u32, layer_count: 1, ..image.range(0, 1) };
            image_barrier(d, cmd, image.handle, range, reused, written);
        }
        d.cmd_copy_buffer_to_image(cmd, staging.handle, image.handle, vk::ImageLayout::TRANSFER_DST_OPTIMAL, &regions);
        for (_, layer) in placed {
            let range =
                vk::ImageSubresourceRange { base_array_layer: *layer as u32, layer_count: 1, ..image.range(0, 1) };
            image_barrier(d, cmd, image.handle, range, written, SAMPLED);
        }
        d.end_command_buffer(cmd).vk("vkEndCommandBuffer")?;
    }
    let cmds = [vk::CommandBufferSubmitInfo::default().command_buffer(cmd)];
    let signal = [vk::SemaphoreSubmitInfo::default()
        .semaphore(shared.generations.handle)
        .value(g)
        .stage_mask(vk::PipelineStageFlags2::ALL_COMMANDS)];
    let submit = vk::SubmitInfo2::default().command_buffer_infos(&cmds).signal_semaphore_infos(&signal);
    device.errors_queue.submit(device, &[submit], vk::Fence::null())?;
    shared.generations.wait(g, u64::MAX)?;
    Ok(())
}

/// A tile's heights as the atlas's texels: 16-bit integers for R16_UNORM (exact: the
/// shader rounds `texel * 65535` back), f32 otherwise.
pub fn texels(heights: &Heights, unorm16: bool, dst: &mut [u8]) -> Result<(), String> {
    let n = dst.len() / if unorm16 { 2 } else { 4 };
    let count = match heights {
        Heights::Unorm16(v) => v.len(),
        Heights::Float32(v) => v.len(),
    };
    if count != n {
        return Err(format!("{count} heights for a layer of {n}"));
    }
    for i in 0..n {
        let h = heights.get(i);
        if unorm16 {
            if h.fract() != 0.0 || !(0.0..=65535.0).contains(&h) {
                return Err(format!("height {h} in a 16-bit archive"));
            }
            dst[2 * i..2 * i + 2].copy_from_slice(&(h as u16).to_ne_bytes());
        } else {
            dst[4 * i..4 * i + 4].copy_from_slice(&h.to_ne_bytes());
        }
    }
    Ok(())
}
