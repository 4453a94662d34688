//! The errors activity (SPEC section 4, seed 000 section 3.2): its own thread and queue,
//! fragment-shader passes only. Per generation it rasterizes `GIE_i` for LOD `i = 1..=n`
//! into mip `i-1` of an R32F image (about `4^n / 3` fragments in all), reduces it to one
//! error per block, and copies only that block-error pyramid to a host-visible buffer.
//! Two slots (error images + readback buffers) are used in turn, by the rules of
//! [`crate::handoff`], so that up to two generations are in flight; a timeline semaphore
//! whose value is the generation number hands each finished one to the draw thread.

use crate::gie::{fragments_per_update, BlockErrors, ErrorParams, GroupErrors};
use crate::gpu_layout::{self as layout, GiePush, ReducePush};
use crate::handoff::{Handoff, Read};
use crate::heightfield::{HeightFormat, Heightfield};
use crate::quadtree::BlockLayout;
use crate::shaders;
use crate::terrain_gpu::TerrainGpu;
use crate::trace::{Trace, ERRORS_TID};
use crate::vk::{
    begin_one_time, host_read_barrier, image_barrier, vk, Buffer, CommandPool, DescriptorPool, DescriptorSetLayout,
    Device, GraphicsPipeline, GraphicsPipelineDesc, Image, ImageUse, ImageView, PipelineLayout, QueryPool,
    TimelineSemaphore, VkError, VkResult, VkResultExt,
};
use std::collections::VecDeque;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Arc, Condvar, Mutex};
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

const GIE_FORMAT: vk::Format = vk::Format::R32_SFLOAT;

/// One finished generation, copied out of its readback buffer.
#[derive(Clone, Debug)]
pub struct Generation {
    pub number: u64,
    pub params: ErrorParams,
    pub errors: BlockErrors,
    /// GPU time of this update (timestamp queries), when the device has timestamps.
    pub gpu_ms: Option<f64>,
}

/// Per-update costs, for stats.
#[derive(Clone, Copy, Debug)]
pub struct UpdateCost {
    pub fragments_shaded: u64,
    pub readback_bytes: u64,
    pub levels: u32,
}

#[derive(Clone, Copy, Debug)]
struct SlotInfo {
    generation: u64,
    params: ErrorParams,
    /// The generation's GPU time, read by the errors thread once it finished: reading
    /// query results can wait for the whole queue on some drivers (lavapipe), which
    /// must not stall the draw thread.
    gpu_ms: Option<f64>,
}

/// The hand-off protocol and what each slot holds, under one lock.
struct HandoffState {
    protocol: Handoff,
    slots: [Option<SlotInfo>; 2],
}

struct Request {
    params: Option<ErrorParams>,
    stop: bool,
}

struct Shared {
    request: Mutex<Request>,
    handoff: Mutex<HandoffState>,
    /// Host events for the errors thread, counted: a new request, a released slot, stop.
    /// (A host-signalled timeline semaphore would let one wait cover the GPU too, but
    /// the validation layers of Debian bookworm time out on those: VVL issue 4649.)
    events: Mutex<u64>,
    events_cv: Condvar,
    /// Notified (with `handoff`) when a generation is published or the thread fails.
    published: Condvar,
    /// Generation `g` is written when this reaches `g`.
    timeline: TimelineSemaphore,
    /// Counts the errors queue's submissions as they complete (each signals one more).
    submissions: TimelineSemaphore,
    /// Each submission waits (on the CPU) for the one before to complete, so that at most
    /// one submission of error work sits ahead of a draw on a shared queue.
    paced: bool,
    readbacks: [Buffer; 2],
    /// The reader's copy of the newest generation it took.
    copy: Mutex<Option<Generation>>,
    failure: Mutex<Option<VkError>>,
    root_lod: u32,
    /// Two timestamps per submission of a generation, per slot.
    queries: Option<QueryPool>,
    /// Per slot: the slot's timestamps copied on the GPU (read after the generation
    /// finished, without vkGetQueryPoolResults, which waits for the queue on lavapipe).
    timestamps: Vec<Buffer>,
    /// True while the thread waits with nothing to do.
    idle: AtomicBool,
    /// The host events the thread had seen when it last found nothing to do.
    idle_seen: AtomicU64,
    /// Most generations in flight on the GPU at once.
    most_in_flight: AtomicU64,
    /// Test hook: fail with ERROR_DEVICE_LOST when this generation is submitted (0: never).
    inject_device_lost_at: AtomicU64,
    trace: Trace,
}

impl Shared {
    /// Host events so far. Read before looking at the shared state, then wait for more:
    /// an event that comes in between is not missed.
    fn seen(&self) -> u64 {
        *self.events.lock().unwrap()
    }

    /// Wakes the errors thread if it waits for host events.
    fn notify(&self) {
        *self.events.lock().unwrap() += 1;
        self.events_cv.notify_all();
    }
}

/// How the errors thread paces its submissions (`--error-pacing`).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, clap::ValueEnum)]
pub enum Pacing {
    /// Paced exactly when the queue is shared with the draw thread.
    #[default]
    Auto,
    /// Each submission waits for the one before: draws interleave on a shared queue, and
    /// a second generation only queues once the first is done.
    Paced,
    /// Submissions go as soon as they are recorded: two generations in flight on the
    /// errors queue (the separate-queue behaviour; tests force it on a shared queue).
    Free,
}

/// Handle held by the draw thread.
pub struct ErrorsActivity {
    shared: Arc<Shared>,
    thread: Option<JoinHandle<()>>,
    pub cost: UpdateCost,
}

/// GPU objects of one slot.
struct Slot {
    gie: Image,
    gie_mips: Vec<ImageView>,
    tbe: Option<Image>,
    tbe_mips: Vec<ImageView>,
    gie_sets: Vec<vk::DescriptorSet>,
    reduce_set: vk::DescriptorSet,
    /// A generation is recorded into up to [`CHUNKS`] command buffers, submitted one
    /// after another, so that draw submissions can run in between on a shared queue.
    cmds: Vec<vk::CommandBuffer>,
}

/// Submissions a generation is split into, at most (about equal fragment counts).
const CHUNKS: usize = 4;
/// Timestamp queries per slot: a pair per submission.
const QUERIES_PER_SLOT: u32 = 2 * CHUNKS as u32;

/// Everything the errors thread owns on the GPU.
struct ErrorsGpu {
    device: Arc<Device>,
    terrain: Arc<TerrainGpu>,
    hf: Arc<Heightfield>,
    layout: BlockLayout,
    slots: Vec<Slot>,
    /// Owned by `Shared`, which outlives this (the thread holds an Arc to it).
    queries: Option<vk::QueryPool>,
    /// Per slot, where the slot's timestamps are copied (owned by `Shared` too).
    timestamp_buffers: Vec<vk::Buffer>,
    /// The GIE pass per error mode: `[paper, strict]`.
    gie_pipelines: [GraphicsPipeline; 2],
    reduce_pipeline: GraphicsPipeline,
    gie_layout: PipelineLayout,
    reduce_layout: PipelineLayout,
    _gie_set_layout: DescriptorSetLayout,
    _reduce_set_layout: DescriptorSetLayout,
    _pool: DescriptorPool,
    _dummy: Image,
    commands: CommandPool,
}

/// Copy regions for every mip of a square R32F image, packed one after another from
/// `offset` (mip 0 first, rows tightly packed): the block-error layout of the README.
fn mip_copy_regions(image: &Image, offset: u64) -> Vec<vk::BufferImageCopy> {
    let mut at = offset;
    (0..image.mip_levels)
        .map(|mip| {
            let side = (image.extent.width >> mip).max(1);
            let region = vk::BufferImageCopy::default()
                .buffer_offset(at)
                .image_subresource(vk::ImageSubresourceLayers {
                    aspect_mask: vk::ImageAspectFlags::COLOR,
                    mip_level: mip,
                    base_array_layer: 0,
                    layer_count: 1,
                })
                .image_extent(vk::Extent3D { width: side, height: side, depth: 1 });
            at += side as u64 * side as u64 * 4;
            region
        })
        .collect()
}

fn readback_bytes(root_lod: u32) -> u64 {
    // Header and trailer words hold the generation number (torn-read check).
    (BlockErrors::packed_len(root_lod) * 4 + 8) as u64
}

impl ErrorsGpu {
    fn new(
        device: &Arc<Device>,
        terrain: Arc<TerrainGpu>,
        hf: Arc<Heightfield>,
        block_layout: BlockLayout,
    ) -> VkResult<Self> {
        let n = hf.n;
        let root = block_layout.root_lod();
        let frag = vk::ShaderStageFlags::FRAGMENT;
        let sampler = vk::DescriptorType::COMBINED_IMAGE_SAMPLER;
        let gie_set_layout = DescriptorSetLayout::new(
            device,
            &[
                (layout::GIE_BINDING_HEIGHTS, sampler, frag),
                (layout::GIE_BINDING_PREV, sampler, frag),
                (layout::GIE_BINDING_MINMAX, sampler, frag),
                (layout::GIE_BINDING_DEVIATION, sampler, frag),
            ],
        )?;
        let reduce_set_layout = DescriptorSetLayout::new(device, &[(layout::REDUCE_BINDING_GIE, sampler, frag)])?;
        let gie_layout = PipelineLayout::new(device, &gie_set_layout, std::mem::size_of::<GiePush>() as u32, frag)?;
        let reduce_layout =
            PipelineLayout::new(device, &reduce_set_layout, std::mem::size_of::<ReducePush>() as u32, frag)?;
        let desc = |fs, l| GraphicsPipelineDesc::fullscreen_pass(fs, GIE_FORMAT, l);
        let gie = |strict| {
            GraphicsPipeline::new(
                device,
                &GraphicsPipelineDesc {
                    specialization: &[(layout::SPEC_STRICT_ERRORS, strict)],
                    ..desc(shaders::GIE_FRAG, &gie_layout)
                },
            )
        };
        let gie_pipelines = [gie(false)?, gie(true)?];
        let reduce_pipeline = GraphicsPipeline::new(device, &desc(shaders::BLOCK_REDUCE_FRAG, &reduce_layout))?;
        let pool = DescriptorPool::new(device, 2 * (n + 1), &[(sampler, 2 * (4 * n + 1))])?;
        let commands = CommandPool::new(device, device.errors_queue.family)?;

        // GIE of LOD 1 has no previous level; its binding still needs a valid image.
        let usage_rt =
            vk::ImageUsageFlags::COLOR_ATTACHMENT | vk::ImageUsageFlags::SAMPLED | vk::ImageUsageFlags::TRANSFER_SRC;
        let one = vk::Extent2D { width: 1, height: 1 };
        let dummy = Image::new(
            device,
            "GIE placeholder",
            one,
            GIE_FORMAT,
            1,
            vk::ImageUsageFlags::SAMPLED | vk::ImageUsageFlags::TRANSFER_DST,
            false,
        )?;
        let upload_pool = CommandPool::new(device, device.draw_queue.family)?;
        crate::terrain_gpu::upload(device, &upload_pool, &dummy, &[&0f32.to_le_bytes()])?;

        let gie_side = 1u32 << (n - 1);
        let mut slots = Vec::new();
        for s in 0..2 {
            let gie = Image::new(
                device,
                &format!("GIE pyramid {s}"),
                vk::Extent2D { width: gie_side, height: gie_side },
                GIE_FORMAT,
                n,
                usage_rt,
                false,
            )?;
            let gie_mips = (0..n).map(|m| gie.mip_view(m, 1)).collect::<VkResult<Vec<_>>>()?;
            let (tbe, tbe_mips) = if root > 0 {
                let side = 1u32 << (root - 1);
                let img = Image::new(
                    device,
                    &format!("block errors {s}"),
                    vk::Extent2D { width: side, height: side },
                    GIE_FORMAT,
                    root,
                    vk::ImageUsageFlags::COLOR_ATTACHMENT | vk::ImageUsageFlags::TRANSFER_SRC,
                    false,
                )?;
                let mips = (0..root).map(|m| img.mip_view(m, 1)).collect::<VkResult<Vec<_>>>()?;
                (Some(img), mips)
            } else {
                (None, Vec::new())
            };
            let mut gie_sets = Vec::new();
            for lod in 1..=n {
                let set = pool.allocate(&gie_set_layout)?;
                let prev = if lod == 1 { dummy.view } else { gie_mips[(lod - 2) as usize].handle };
                pool.write(
                    set,
                    &[
                        (layout::GIE_BINDING_HEIGHTS, terrain.heights.view, terrain.nearest.handle),
                        (layout::GIE_BINDING_PREV, prev, terrain.nearest.handle),
                        (layout::GIE_BINDING_MINMAX, terrain.minmax.view, terrain.nearest.handle),
                        (layout::GIE_BINDING_DEVIATION, terrain.deviation.view, terrain.nearest.handle),
                    ],
                    &[],
                );
                gie_sets.push(set);
            }
            let reduce_set = pool.allocate(&reduce_set_layout)?;
            pool.write(reduce_set, &[(layout::REDUCE_BINDING_GIE, gie.view, terrain.nearest.handle)], &[]);
            let cmds = (0..CHUNKS).map(|_| commands.allocate()).collect::<VkResult<Vec<_>>>()?;
            slots.push(Slot { gie, gie_mips, tbe, tbe_mips, gie_sets, reduce_set, cmds });
        }
        Ok(ErrorsGpu {
            device: device.clone(),
            terrain,
            hf,
            layout: block_layout,
            slots,
            queries: None,
            timestamp_buffers: Vec::new(),
            gie_pipelines,
            reduce_pipeline,
            gie_layout,
            reduce_layout,
            _gie_set_layout: gie_set_layout,
            _reduce_set_layout: reduce_set_layout,
            _pool: pool,
            _dummy: dummy,
            commands,
        })
    }

    /// Draws one full-target triangle into `view` (a `side` x `side` mip), shading only
    /// the rows `rows` (a band of a pass split over several submissions).
    #[allow(clippy::too_many_arguments)]
    fn pass(
        &self,
        cmd: vk::CommandBuffer,
        view: vk::ImageView,
        side: u32,
        rows: std::ops::Range<u32>,
        (pipeline, pl): (&GraphicsPipeline, &PipelineLayout),
        set: vk::DescriptorSet,
        push: &[u8],
    ) {
        let d = &self.device.raw;
        let area = vk::Rect2D {
            offset: vk::Offset2D { x: 0, y: rows.start as i32 },
            extent: vk::Extent2D { width: side, height: rows.end - rows.start },
        };
        let att = [vk::RenderingAttachmentInfo::default()
            .image_view(view)
            .image_layout(vk::ImageLayout::COLOR_ATTACHMENT_OPTIMAL)
            .load_op(vk::AttachmentLoadOp::DONT_CARE)
            .store_op(vk::AttachmentStoreOp::STORE)];
        let info = vk::RenderingInfo::default().render_area(area).layer_count(1).color_attachments(&att);
        // SAFETY: `cmd` is recording on the errors thread; all objects outlive the submission.
        unsafe {
            d.cmd_begin_rendering(cmd, &info);
            d.cmd_set_viewport(
                cmd,
                0,
                &[vk::Viewport {
                    x: 0.0,
                    y: 0.0,
                    width: side as f32,
                    height: side as f32,
                    min_depth: 0.0,
                    max_depth: 1.0,
                }],
            );
            d.cmd_set_scissor(cmd, 0, &[area]);
            d.cmd_bind_pipeline(cmd, vk::PipelineBindPoint::GRAPHICS, pipeline.handle);
            d.cmd_bind_descriptor_sets(cmd, vk::PipelineBindPoint::GRAPHICS, pl.handle, 0, &[set], &[]);
            d.cmd_push_constants(cmd, pl.handle, vk::ShaderStageFlags::FRAGMENT, 0, push);
            d.cmd_draw(cmd, 3, 1, 0, 0);
            d.cmd_end_rendering(cmd);
        }
    }

    fn barrier(&self, cmd: vk::CommandBuffer, image: &Image, mip: u32, count: u32, from: ImageUse, to: ImageUse) {
        // SAFETY: recording on this thread; the slot's images outlive the submission.
        unsafe { image_barrier(&self.device.raw, cmd, image.handle, image.range(mip, count), from, to) };
    }

    /// Records generation `g` into its slot's command buffers: the GIE passes split in
    /// row bands over up to [`CHUNKS`] of them, the reduction, readback and timestamps in
    /// the last. Returns the buffers to submit, in order.
    fn record(
        &self,
        slot_index: usize,
        g: u64,
        p: &ErrorParams,
        readback: &Buffer,
        gie_dump: Option<&Buffer>,
    ) -> VkResult<Vec<vk::CommandBuffer>> {
        let slot = &self.slots[slot_index];
        let d = &self.device.raw;
        let mut used = 1;
        let mut cmd = slot.cmds[0];
        let n = self.hf.n;
        let root = self.layout.root_lod();
        // SAFETY: the slot's previous submissions (generation g-2) have completed: the
        // hand-off starts g only once g-2 is finished (`Handoff::can_start`).
        unsafe {
            begin_one_time(d, cmd)?;
        }
        // Two timestamps per submission: the update's GPU time is the sum over them,
        // without the draws that ran in between.
        let q0 = QUERIES_PER_SLOT * slot_index as u32;
        if let Some(pool) = self.queries {
            // SAFETY: recording; these queries belong to this slot only.
            unsafe {
                d.cmd_reset_query_pool(cmd, pool, q0, QUERIES_PER_SLOT);
                d.cmd_write_timestamp2(cmd, vk::PipelineStageFlags2::TOP_OF_PIPE, pool, q0);
            }
        }
        let frag = vk::PipelineStageFlags2::FRAGMENT_SHADER;
        let color = vk::PipelineStageFlags2::COLOR_ATTACHMENT_OUTPUT;
        let copy = vk::PipelineStageFlags2::COPY;
        let read = vk::AccessFlags2::SHADER_SAMPLED_READ;
        let write = vk::AccessFlags2::COLOR_ATTACHMENT_WRITE;
        let rt = vk::ImageLayout::COLOR_ATTACHMENT_OPTIMAL;
        let ro = vk::ImageLayout::SHADER_READ_ONLY_OPTIMAL;
        // Earlier generations on this queue read (GIE) or copied (TBE) these images.
        self.barrier(
            cmd,
            &slot.gie,
            0,
            n,
            (frag | color | vk::PipelineStageFlags2::COPY, write, vk::ImageLayout::UNDEFINED),
            (color, write, rt),
        );
        let unorm = (self.hf.format == HeightFormat::Unorm16) as i32;
        let gie_pipeline = &self.gie_pipelines[(p.mode == crate::gie::ErrorMode::Strict) as usize];
        // About equal fragment counts per submission; one pass may span several.
        let total: u64 = (1..=n).map(|lod| 1u64 << (2 * (n - lod))).sum();
        let budget = total.div_ceil(CHUNKS as u64).max(1);
        let mut in_chunk = 0u64;
        for lod in 1..=n {
            let side = 1u32 << (n - lod);
            let push = GiePush {
                level: [lod as i32, n as i32, 0, unorm],
                extent: [self.hf.width as i32, self.hf.height as i32, side as i32, 0],
                camera: [p.camera.x, p.camera.y, p.camera.z, p.kappa],
                params: [self.hf.spacing, self.hf.height_scale, p.near, 0.0],
            };
            let band = ((budget / side as u64).max(1) as u32).min(side);
            let mut row = 0;
            while row < side {
                let rows = row..(row + band).min(side);
                let fragments = (rows.end - rows.start) as u64 * side as u64;
                if in_chunk > 0 && in_chunk + fragments > budget && used < slot.cmds.len() {
                    // SAFETY: `cmd` is recording; the next buffer of this slot is idle
                    // (same argument as for the first).
                    unsafe {
                        let q = q0 + 2 * used as u32;
                        if let Some(pool) = self.queries {
                            d.cmd_write_timestamp2(cmd, vk::PipelineStageFlags2::BOTTOM_OF_PIPE, pool, q - 1);
                        }
                        d.end_command_buffer(cmd).vk("vkEndCommandBuffer")?;
                        cmd = slot.cmds[used];
                        begin_one_time(d, cmd)?;
                        if let Some(pool) = self.queries {
                            d.cmd_write_timestamp2(cmd, vk::PipelineStageFlags2::TOP_OF_PIPE, pool, q);
                        }
                    }
                    used += 1;
                    in_chunk = 0;
                }
                self.pass(
                    cmd,
                    slot.gie_mips[(lod - 1) as usize].handle,
                    side,
                    rows.clone(),
                    (gie_pipeline, &self.gie_layout),
                    slot.gie_sets[(lod - 1) as usize],
                    bytemuck::bytes_of(&push),
                );
                in_chunk += fragments;
                row = rows.end;
            }
            self.barrier(cmd, &slot.gie, lod - 1, 1, (color, write, rt), (frag, read, ro));
        }
        let data_bytes = BlockErrors::packed_len(root) as u64 * 4;
        if let Some(tbe) = &slot.tbe {
            self.barrier(cmd, tbe, 0, root, (copy | color, write, vk::ImageLayout::UNDEFINED), (color, write, rt));
            for j in 1..=root {
                let push = ReducePush { level: [j as i32, j as i32 - 1, (self.layout.k() - 1) as i32, 0] };
                self.pass(
                    cmd,
                    slot.tbe_mips[(j - 1) as usize].handle,
                    1u32 << (root - j),
                    0..1u32 << (root - j),
                    (&self.reduce_pipeline, &self.reduce_layout),
                    slot.reduce_set,
                    bytemuck::bytes_of(&push),
                );
            }
            self.barrier(
                cmd,
                tbe,
                0,
                root,
                (color, write, rt),
                (copy, vk::AccessFlags2::TRANSFER_READ, vk::ImageLayout::TRANSFER_SRC_OPTIMAL),
            );
            // After the generation header word.
            let regions = mip_copy_regions(tbe, 4);
            // SAFETY: recording; the readback slot is not read by the draw thread (the
            // hand-off protocol guarantees it).
            unsafe {
                d.cmd_copy_image_to_buffer(
                    cmd,
                    tbe.handle,
                    vk::ImageLayout::TRANSFER_SRC_OPTIMAL,
                    readback.handle,
                    &regions,
                )
            };
        }
        if let Some(dump) = gie_dump {
            // Tests compare every GIE texel with the reference: copy all mips, LOD 1 first.
            self.barrier(
                cmd,
                &slot.gie,
                0,
                n,
                (frag, read, ro),
                (copy, vk::AccessFlags2::TRANSFER_READ, vk::ImageLayout::TRANSFER_SRC_OPTIMAL),
            );
            let regions = mip_copy_regions(&slot.gie, 0);
            // SAFETY: recording; `dump` is owned by the caller, who waits for completion.
            unsafe {
                d.cmd_copy_image_to_buffer(
                    cmd,
                    slot.gie.handle,
                    vk::ImageLayout::TRANSFER_SRC_OPTIMAL,
                    dump.handle,
                    &regions,
                );
                host_read_barrier(d, cmd, dump.handle, (copy, vk::AccessFlags2::TRANSFER_WRITE));
            }
        }
        // SAFETY: recording; fills touch only the header and trailer words.
        unsafe {
            let before = [vk::BufferMemoryBarrier2::default()
                .src_stage_mask(vk::PipelineStageFlags2::HOST)
                .src_access_mask(vk::AccessFlags2::HOST_READ)
                .dst_stage_mask(copy | vk::PipelineStageFlags2::CLEAR)
                .dst_access_mask(vk::AccessFlags2::TRANSFER_WRITE)
                .buffer(readback.handle)
                .size(vk::WHOLE_SIZE)];
            d.cmd_pipeline_barrier2(cmd, &vk::DependencyInfo::default().buffer_memory_barriers(&before));
            d.cmd_fill_buffer(cmd, readback.handle, 0, 4, g as u32);
            d.cmd_fill_buffer(cmd, readback.handle, 4 + data_bytes, 4, g as u32);
            let written = (copy | vk::PipelineStageFlags2::CLEAR, vk::AccessFlags2::TRANSFER_WRITE);
            host_read_barrier(d, cmd, readback.handle, written);
            if let Some(pool) = self.queries {
                let last = q0 + 2 * used as u32 - 1;
                d.cmd_write_timestamp2(cmd, vk::PipelineStageFlags2::BOTTOM_OF_PIPE, pool, last);
                if let Some(&buffer) = self.timestamp_buffers.get(slot_index) {
                    // All of this generation's timestamps, copied once the GPU has them.
                    crate::vk::record_query_copy(d, cmd, pool, q0, 2 * used as u32, buffer, 0);
                }
            }
            d.end_command_buffer(cmd).vk("vkEndCommandBuffer")?;
        }
        Ok(slot.cmds[..used].to_vec())
    }
}

impl Drop for ErrorsGpu {
    fn drop(&mut self) {
        for s in &self.slots {
            for &c in &s.cmds {
                self.commands.free(c);
            }
        }
        let _ = &self.terrain;
    }
}

/// Computes one generation synchronously on the errors queue and returns every GIE
/// texel as well as the block errors (for tests and `errors --dump-gie`).
pub fn compute_once(
    device: &Arc<Device>,
    terrain: Arc<TerrainGpu>,
    hf: Arc<Heightfield>,
    block_layout: BlockLayout,
    params: &ErrorParams,
) -> VkResult<(GroupErrors, BlockErrors)> {
    let n = hf.n;
    let root = block_layout.root_lod();
    let gpu = ErrorsGpu::new(device, terrain, hf, block_layout)?;
    let readback = Buffer::new(
        device,
        "block-error readback",
        readback_bytes(root),
        vk::BufferUsageFlags::TRANSFER_DST,
        gpu_allocator::MemoryLocation::GpuToCpu,
    )?;
    let texels: u64 = (1..=n).map(|i| 1u64 << (2 * (n - i))).sum();
    let dump = Buffer::new(
        device,
        "GIE dump",
        texels * 4,
        vk::BufferUsageFlags::TRANSFER_DST,
        gpu_allocator::MemoryLocation::GpuToCpu,
    )?;
    let timeline = TimelineSemaphore::new(device, 0)?;
    let cmds: Vec<_> = gpu
        .record(1, 1, params, &readback, Some(&dump))?
        .into_iter()
        .map(|c| vk::CommandBufferSubmitInfo::default().command_buffer(c))
        .collect();
    let signal = [vk::SemaphoreSubmitInfo::default()
        .semaphore(timeline.handle)
        .value(1)
        .stage_mask(vk::PipelineStageFlags2::ALL_COMMANDS)];
    let submit = [vk::SubmitInfo2::default().command_buffer_infos(&cmds).signal_semaphore_infos(&signal)];
    device.errors_queue.submit(device, &submit, vk::Fence::null())?;
    timeline.wait(1, u64::MAX)?;
    let data: Vec<f32> = bytemuck::pod_collect_to_vec(dump.mapped()?);
    let mut levels = Vec::new();
    let mut at = 0;
    for lod in 1..=n {
        let len = 1usize << (2 * (n - lod));
        levels.push(data[at..at + len].to_vec());
        at += len;
    }
    let rb = readback.mapped()?;
    let len = BlockErrors::packed_len(root);
    let blocks: Vec<f32> = bytemuck::pod_collect_to_vec(&rb[4..4 + len * 4]);
    Ok((GroupErrors { n, levels }, BlockErrors::from_packed(root, &blocks)))
}

impl ErrorsActivity {
    /// Starts the errors thread. Nothing is computed until [`ErrorsActivity::request`].
    pub fn start(
        device: &Arc<Device>,
        terrain: Arc<TerrainGpu>,
        hf: Arc<Heightfield>,
        block_layout: BlockLayout,
    ) -> VkResult<Self> {
        Self::start_with(device, terrain, hf, block_layout, Trace::off(), Pacing::Auto)
    }

    /// Like [`ErrorsActivity::start`], recording the thread's work into `trace`, with the
    /// submissions paced as asked.
    pub fn start_with(
        device: &Arc<Device>,
        terrain: Arc<TerrainGpu>,
        hf: Arc<Heightfield>,
        block_layout: BlockLayout,
        trace: Trace,
        pacing: Pacing,
    ) -> VkResult<Self> {
        let root = block_layout.root_lod();
        let bytes = readback_bytes(root);
        let rb = |i: usize| {
            Buffer::new(
                device,
                &format!("block-error readback {i}"),
                bytes,
                vk::BufferUsageFlags::TRANSFER_DST,
                gpu_allocator::MemoryLocation::GpuToCpu,
            )
        };
        let queries = QueryPool::timestamps(device, 2 * QUERIES_PER_SLOT)?;
        if queries.is_none() {
            tracing::info!("no timestamp queries on this device: error update GPU times are not reported");
        }
        let timestamps = match queries {
            Some(_) => (0..2)
                .map(|i| {
                    Buffer::new(
                        device,
                        &format!("error timestamps {i}"),
                        QUERIES_PER_SLOT as u64 * 8,
                        vk::BufferUsageFlags::TRANSFER_DST,
                        gpu_allocator::MemoryLocation::GpuToCpu,
                    )
                })
                .collect::<VkResult<Vec<_>>>()?,
            None => Vec::new(),
        };
        let paced = match pacing {
            Pacing::Auto => device.queue_mode == crate::vk::QueueMode::Shared,
            Pacing::Paced => true,
            Pacing::Free => false,
        };
        let shared = Arc::new(Shared {
            request: Mutex::new(Request { params: None, stop: false }),
            handoff: Mutex::new(HandoffState { protocol: Handoff::default(), slots: [None, None] }),
            events: Mutex::new(0),
            events_cv: Condvar::new(),
            published: Condvar::new(),
            timeline: TimelineSemaphore::new(device, 0)?,
            submissions: TimelineSemaphore::new(device, 0)?,
            paced,
            readbacks: [rb(0)?, rb(1)?],
            copy: Mutex::new(None),
            failure: Mutex::new(None),
            root_lod: root,
            queries,
            timestamps,
            idle: AtomicBool::new(true),
            idle_seen: AtomicU64::new(0),
            most_in_flight: AtomicU64::new(0),
            inject_device_lost_at: AtomicU64::new(0),
            trace,
        });
        let cost = UpdateCost {
            fragments_shaded: fragments_per_update(hf.n, block_layout.m),
            readback_bytes: bytes,
            levels: hf.n,
        };
        // The GPU objects are created here so that set-up errors reach the caller; the
        // thread then owns them (and its own command pool) exclusively.
        let mut gpu = ErrorsGpu::new(device, terrain, hf, block_layout)?;
        gpu.queries = shared.queries.as_ref().map(|q| q.handle);
        gpu.timestamp_buffers = shared.timestamps.iter().map(|b| b.handle).collect();
        let thread_shared = shared.clone();
        let thread = std::thread::Builder::new()
            .name("errors-activity".into())
            .spawn(move || {
                if let Err(e) = run(gpu, &thread_shared) {
                    *thread_shared.failure.lock().unwrap() =
                        Some(VkError::Thread { stage: "errors activity".into(), cause: Box::new(e) });
                    thread_shared.published.notify_all();
                }
            })
            .map_err(|e| VkError::Setup(format!("cannot start the errors thread: {e}")))?;
        Ok(ErrorsActivity { shared, thread: Some(thread), cost })
    }

    /// Asks for a generation computed with `params`; does nothing if the latest request
    /// already has them (a camera standing still starts no work).
    pub fn request(&self, params: ErrorParams) {
        let changed = {
            let mut r = self.shared.request.lock().unwrap();
            let changed = r.params != Some(params);
            r.params = Some(params);
            changed
        };
        if changed {
            self.shared.notify();
        }
    }

    /// The errors thread's failure, if it failed.
    pub fn check_failure(&self) -> VkResult<()> {
        match &*self.shared.failure.lock().unwrap() {
            Some(e) => Err(e.clone()),
            None => Ok(()),
        }
    }

    /// The newest finished generation newer than `after`, copied out; never blocks on
    /// the GPU (the errors thread publishes a generation once the GPU signalled it).
    pub fn latest(&self, after: u64) -> VkResult<Option<Generation>> {
        self.check_failure()?;
        let s = &self.shared;
        // One reader at a time: the lock is held across the copy.
        let mut copy = s.copy.lock().unwrap();
        let (g, slot, info) = {
            let mut h = s.handoff.lock().unwrap();
            match h.protocol.begin_read() {
                Read::Nothing => return Ok(None),
                Read::Copied(g) => {
                    return Ok(copy.as_ref().filter(|c| c.number == g && g > after).cloned());
                }
                Read::Copy { generation, slot } => (generation, slot, h.slots[slot]),
            }
        };
        if g <= after {
            // Published after the caller's own copy? Cannot be, but keep the slot free.
            s.handoff.lock().unwrap().protocol.end_read(g, false);
            s.notify();
            return Ok(None);
        }
        let bytes = s.readbacks[slot].mapped();
        let read = bytes.map(|bytes| {
            let len = BlockErrors::packed_len(s.root_lod);
            let header = u32::from_le_bytes(bytes[0..4].try_into().unwrap());
            let data: Vec<f32> = bytemuck::pod_collect_to_vec(&bytes[4..4 + len * 4]);
            let trailer = u32::from_le_bytes(bytes[4 + len * 4..8 + len * 4].try_into().unwrap());
            (header, data, trailer)
        });
        let info = info.filter(|i| i.generation == g);
        let taken = match (read, info) {
            (Ok((header, data, trailer)), Some(info)) if header == g as u32 && trailer == g as u32 => Ok(Generation {
                number: g,
                params: info.params,
                errors: BlockErrors::from_packed(s.root_lod, &data),
                gpu_ms: info.gpu_ms,
            }),
            (Err(e), _) => Err(e),
            (Ok((header, _, trailer)), _) => Err(VkError::Setup(format!(
                "hand-off broken: generation {g} read as header {header}, trailer {trailer}"
            ))),
        };
        s.handoff.lock().unwrap().protocol.end_read(g, taken.is_ok());
        // The writer may be waiting for this slot.
        s.notify();
        let taken = taken?;
        *copy = Some(taken.clone());
        Ok(Some(taken))
    }

    /// Requests `params` and blocks until a generation computed with them is finished.
    pub fn wait_for(&self, params: ErrorParams, timeout: Duration) -> VkResult<Generation> {
        // A NaN never equals itself: such a request could never be answered.
        if !(params.camera.is_finite() && params.kappa.is_finite() && params.near.is_finite()) {
            return Err(VkError::Setup(format!("error data requested for a non-finite camera {}", params.camera)));
        }
        self.request(params);
        let start = Instant::now();
        let mut after = 0;
        loop {
            if let Some(g) = self.latest(after)? {
                if g.params == params {
                    return Ok(g);
                }
                after = g.number;
            }
            if start.elapsed() > timeout {
                return Err(VkError::Setup(format!(
                    "errors activity produced no generation for this camera within {:.0} s",
                    timeout.as_secs_f64()
                )));
            }
            let h = self.shared.handoff.lock().unwrap();
            if h.protocol.finished() <= after {
                // Woken when the next one is published (or the thread failed).
                drop(self.shared.published.wait_timeout(h, Duration::from_millis(50)).unwrap());
            }
        }
    }

    /// Test hook: the errors thread fails as if the device were lost when it is about to
    /// submit generation `g`.
    pub fn inject_device_lost_at(&self, g: u64) {
        self.shared.inject_device_lost_at.store(g, Ordering::SeqCst);
    }

    /// Whether the thread has work (a request with new parameters, or a generation in
    /// flight), and generations finished: a watchdog's view of its progress.
    pub fn progress(&self) -> (bool, u64) {
        let done = self.shared.handoff.lock().unwrap().protocol.finished();
        (!self.shared.idle.load(Ordering::SeqCst), done)
    }

    /// True once the thread has looked at every request made so far and found nothing
    /// to do (no new parameters, nothing in flight): what "a request started no work"
    /// is checked with, instead of a sleep.
    pub fn settled(&self) -> bool {
        let events = self.shared.seen();
        self.shared.idle.load(Ordering::SeqCst) && self.shared.idle_seen.load(Ordering::SeqCst) >= events
    }

    /// Whether each submission waits for the one before (`--error-pacing`).
    pub fn paced(&self) -> bool {
        self.shared.paced
    }

    /// Generations started so far (recorded; some may still be in flight).
    pub fn started(&self) -> u64 {
        self.shared.handoff.lock().unwrap().protocol.started()
    }

    /// Most generations that were in flight on the GPU at once (1 when paced; 2 when
    /// requests come faster than updates on a separate queue).
    pub fn most_in_flight(&self) -> u64 {
        self.shared.most_in_flight.load(Ordering::SeqCst)
    }

    /// The generation counter (timeline value).
    pub fn counter(&self) -> VkResult<u64> {
        self.shared.timeline.value()
    }

    /// Stops and joins the errors thread; reports its failure if it had one.
    pub fn stop(mut self) -> VkResult<()> {
        self.shutdown();
        self.check_failure()
    }

    fn shutdown(&mut self) {
        self.shared.request.lock().unwrap().stop = true;
        self.shared.notify();
        if let Some(t) = self.thread.take() {
            let _ = t.join();
        }
    }
}

impl Drop for ErrorsActivity {
    fn drop(&mut self) {
        self.shutdown();
    }
}

/// A generation recorded and not yet published.
struct InFlight {
    g: u64,
    slot: usize,
    cmds: Vec<vk::CommandBuffer>,
    /// Submissions made so far.
    submitted: usize,
    /// The value on `Shared::submissions` that its last submission signals, once made.
    last_signal: u64,
    started: Instant,
}

impl InFlight {
    fn all_submitted(&self) -> bool {
        self.submitted == self.cmds.len()
    }
}

/// The errors thread. Whatever ends it, the GPU is done with its objects before they are
/// dropped.
fn run(gpu: ErrorsGpu, s: &Shared) -> VkResult<()> {
    let mut submissions = 0u64;
    let result = event_loop(&gpu, s, &mut submissions);
    if submissions > 0 {
        // A lost device answers at once; a hung one is given 10 s.
        let _ = s.submissions.wait(submissions, 10_000_000_000);
    }
    result
}

/// The errors thread's loop over the request, the hand-off and the GPU: it publishes
/// what the GPU finished, submits the next part of a generation when pacing lets it go,
/// starts a generation for new parameters when the hand-off has a slot for it, and
/// otherwise sleeps until the GPU or the host (a request, a released slot, stop) wakes
/// it. `submissions` is the value the last submission signals on `s.submissions`.
fn event_loop(gpu: &ErrorsGpu, s: &Shared, submissions: &mut u64) -> VkResult<()> {
    let mut flight: VecDeque<InFlight> = VecDeque::new();
    // Parameters of the newest generation started.
    let mut last: Option<ErrorParams> = None;
    loop {
        // Read before looking at the shared state, so that no event in between is missed.
        let seen = s.seen();
        // Submissions complete in order; a generation is done when its last one is.
        let completed = s.submissions.value()?;
        while flight.front().is_some_and(|f| f.all_submitted() && f.last_signal <= completed) {
            publish(gpu, s, &flight.pop_front().expect("front"))?;
        }
        let (stop, params) = {
            let r = s.request.lock().unwrap();
            (r.stop, r.params)
        };
        if stop {
            return Ok(());
        }
        let fresh = params.filter(|p| Some(*p) != last);
        let queue_ready = !s.paced || completed >= *submissions;
        if let Some(next) = flight.iter().position(|f| !f.all_submitted()) {
            if queue_ready {
                if flight[next].submitted == 0 {
                    // Generations on the GPU once this one is: the earlier ones whose
                    // last submission has not completed, and this one.
                    let earlier = flight.iter().take(next).filter(|e| e.last_signal > completed).count();
                    s.most_in_flight.fetch_max(1 + earlier as u64, Ordering::SeqCst);
                }
                let f = &mut flight[next];
                submit_next(gpu, s, f, submissions)?;
                continue;
            }
        } else if let Some(p) = fresh {
            let started = {
                let mut h = s.handoff.lock().unwrap();
                h.protocol.can_start().then(|| {
                    let g = h.protocol.start();
                    let info = SlotInfo { generation: g, params: p, gpu_ms: None };
                    h.slots[Handoff::slot(g)] = Some(info);
                    g
                })
            };
            if let Some(g) = started {
                s.idle.store(false, Ordering::SeqCst);
                if s.inject_device_lost_at.load(Ordering::SeqCst) == g {
                    return Err(vk::Result::ERROR_DEVICE_LOST)
                        .vk("vkQueueSubmit2 (injected fault)")
                        .map_err(|e| VkError::Thread { stage: format!("generation {g}"), cause: Box::new(e) });
                }
                let slot = Handoff::slot(g);
                let begun = Instant::now();
                let cmds = gpu.record(slot, g, &p, &s.readbacks[slot], None)?;
                flight.push_back(InFlight { g, slot, cmds, submitted: 0, last_signal: 0, started: begun });
                last = Some(p);
                continue;
            }
        }
        // Nothing to do now: sleep until the GPU or the host has news.
        let nothing = flight.is_empty() && fresh.is_none();
        if nothing {
            s.idle_seen.store(seen, Ordering::SeqCst);
        }
        s.idle.store(nothing, Ordering::SeqCst);
        if flight.is_empty() {
            let events = s.events.lock().unwrap();
            if *events == seen {
                // The timeout only bounds the damage of a lost wake-up.
                drop(s.events_cv.wait_timeout(events, Duration::from_millis(100)).unwrap());
            }
        } else {
            // GPU work in flight: wait for the first completion that matters (the oldest
            // generation's last submission, or the submission the next one paces on).
            // One semaphore: lavapipe's wait for any of several spins on a core. Unpaced,
            // look at host events every 2 ms meanwhile (a request that can start a
            // second generation, a released slot); paced, nothing can be submitted
            // before this completes anyway.
            let next = match flight.front() {
                Some(f) if f.all_submitted() => f.last_signal,
                _ => *submissions,
            };
            s.submissions.wait(next, if s.paced { 100_000_000 } else { HOST_LOOK_NS })?;
        }
    }
}

/// How often the unpaced errors thread looks at host events while it waits for the GPU.
const HOST_LOOK_NS: u64 = 2_000_000;

/// Submits `f`'s next command buffer. Each submission signals one more on
/// `s.submissions`; the last also signals generation `f.g` on the timeline.
fn submit_next(gpu: &ErrorsGpu, s: &Shared, f: &mut InFlight, submissions: &mut u64) -> VkResult<()> {
    let last = f.submitted + 1 == f.cmds.len();
    *submissions += 1;
    if last {
        f.last_signal = *submissions;
    }
    let cmds = [vk::CommandBufferSubmitInfo::default().command_buffer(f.cmds[f.submitted])];
    let all = vk::PipelineStageFlags2::ALL_COMMANDS;
    let mut signal =
        vec![vk::SemaphoreSubmitInfo::default().semaphore(s.submissions.handle).value(*submissions).stage_mask(all)];
    if last {
        signal.push(vk::SemaphoreSubmitInfo::default().semaphore(s.timeline.handle).value(f.g).stage_mask(all));
    }
    let submit = [vk::SubmitInfo2::default().command_buffer_infos(&cmds).signal_semaphore_infos(&signal)];
    let (asked, got) = gpu.device.errors_queue.submit_timed(&gpu.device, &submit, vk::Fence::null())?;
    s.trace.complete(ERRORS_TID, "wait (queue lock)", asked, got, serde_json::json!({"generation": f.g}));
    f.submitted += 1;
    if last {
        s.trace.instant(
            ERRORS_TID,
            "submit (errors queue)",
            serde_json::json!({"generation": f.g, "signals": f.g, "submissions": f.cmds.len()}),
        );
    }
    Ok(())
}

/// Generation `f.g` is done on the GPU: reads its GPU time and hands it to the reader.
fn publish(gpu: &ErrorsGpu, s: &Shared, f: &InFlight) -> VkResult<()> {
    // The generation's GPU time (sum over its submissions) and GPU spans; the slot's
    // queries are not reset before g + 2 starts, which needs g published.
    let shared = gpu.device.queue_mode == crate::vk::QueueMode::Shared;
    let mut gpu_ms = None;
    if let (Some(q), Some(buf)) = (&s.queries, s.timestamps.get(f.slot)) {
        let ticks: Vec<u64> = bytemuck::pod_collect_to_vec(&buf.mapped()?[..f.cmds.len() * 16]);
        let mut sum = 0.0;
        for (c, t) in ticks.chunks(2).enumerate() {
            sum += q.ms([t[0], t[1]]);
            let args = serde_json::json!({"generation": f.g, "submission": c});
            s.trace.gpu_span(s.trace.gpu_tid(true, shared), "error passes", [t[0], t[1]], args);
        }
        gpu_ms = Some(sum);
    }
    // Traced before the reader can see it, so that the hand-off arrow never points back.
    if s.trace.enabled() {
        s.trace.flow(ERRORS_TID, true, f.g);
    }
    s.trace.complete(
        ERRORS_TID,
        "generation",
        f.started,
        Instant::now(),
        serde_json::json!({"generation": f.g, "slot": f.slot}),
    );
    s.trace.counter("errors timeline (signalled)", f.g);
    {
        let mut h = s.handoff.lock().unwrap();
        if let Some(info) = h.slots[f.slot].as_mut() {
            info.gpu_ms = gpu_ms;
        }
        h.protocol.finish(f.g);
        s.published.notify_all();
    }
    Ok(())
}
