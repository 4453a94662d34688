//! The errors activity's GPU work (SPEC section 4): per generation, one fragment pass
//! per LOD rasterizes `GIE_i` into mip `i-1` of an R32F image, further passes reduce it
//! to one error per block, and only that block-error pyramid is copied to a host-visible
//! buffer. Owned and recorded by the errors thread ([`crate::errors::activity`]).

use crate::gpu::layout::{self as layout, GiePush, ReducePush};
use crate::gpu::shaders;
use crate::gpu::terrain::TerrainGpu;
use crate::lod::block::BlockLayout;
use crate::lod::gie::{BlockErrors, ErrorParams, GroupErrors};
use crate::lod::heightfield::{HeightFormat, Heightfield};
use crate::vk::{
    begin_one_time, host_read_barrier, image_barrier, vk, Buffer, CommandPool, DescriptorPool, DescriptorSetLayout,
    Device, GraphicsPipeline, GraphicsPipelineDesc, Image, ImageUse, ImageView, PipelineLayout, QueryPool,
    TimelineSemaphore, VkResult, VkResultExt,
};
use std::sync::Arc;

const GIE_FORMAT: vk::Format = vk::Format::R32_SFLOAT;

/// GPU objects of one slot.
pub(crate) struct Slot {
    gie: Image,
    gie_mips: Vec<ImageView>,
    tbe: Option<Image>,
    tbe_mips: Vec<ImageView>,
    gie_sets: Vec<vk::DescriptorSet>,
    reduce_set: vk::DescriptorSet,
    /// A generation is recorded into up to [`MAX_PARTS`] command buffers, submitted one
    /// after another, so that draw submissions can run in between on a shared queue.
    cmds: Vec<vk::CommandBuffer>,
}

/// Submissions a generation is split into, at most (about equal costs, the reduction
/// included; the errors thread chooses how many, `activity::parts_for`). On a shared
/// queue each runs between two frames, so one submission is what a frame can be delayed
/// by: 4 fixed parts left the 4k flyover's frames up to 56 ms late, the reduction and a
/// quarter of the passes in one.
pub(crate) const MAX_PARTS: usize = 16;
/// What one fragment of the block reduction costs, in GIE fragments: it reads `(k-1)^2`
/// texels where a strict GIE fragment reads two and computes a distance (measured on
/// the 4k flyover: the reduction took a third of the passes' time for as many texels).
fn reduce_weight(k: usize) -> u64 {
    ((k - 1) * (k - 1)).div_ceil(4) as u64
}

/// One pass of a generation to split: `width x height` fragments of `cost` each.
#[derive(Clone, Copy, Debug, PartialEq)]
pub(crate) struct PassSize {
    pub width: u32,
    pub height: u32,
    pub cost: u64,
}

/// Rows `rows` of pass `pass`, recorded into submission `part`.
#[derive(Clone, Debug, PartialEq)]
pub(crate) struct Band {
    pub pass: usize,
    pub rows: std::ops::Range<u32>,
    pub part: usize,
}

/// Splits `passes`, in order, into row bands over at most `parts` submissions of about
/// equal cost. Bands are a quarter of an equal share (or one row, where a row costs
/// more; a whole pass with one part); a submission is closed when the next band would
/// take it past its share of what is left, so the last one does not collect what the
/// others left. Every row of every pass is in exactly one band, in order, and the parts
/// never go down.
pub(crate) fn split_passes(passes: &[PassSize], parts: usize) -> Vec<Band> {
    let parts = parts.max(1);
    let cost_of = |p: &PassSize| u64::from(p.width) * u64::from(p.height) * p.cost;
    let mut left: u64 = passes.iter().map(cost_of).sum();
    // One part: whole passes, one render pass each.
    let band_budget = if parts == 1 { u64::MAX } else { (left.div_ceil(parts as u64) / 4).max(1) };
    let (mut part, mut in_part) = (0, 0u64);
    let mut budget = left.div_ceil(parts as u64);
    let mut out = Vec::new();
    for (pass, p) in passes.iter().enumerate() {
        let row_cost = u64::from(p.width) * p.cost;
        let band = ((band_budget / row_cost.max(1)).max(1) as u32).min(p.height.max(1));
        let mut row = 0;
        while row < p.height {
            let rows = row..(row + band).min(p.height);
            let cost = u64::from(rows.end - rows.start) * row_cost;
            if in_part > 0 && in_part + cost > budget && part + 1 < parts {
                part += 1;
                in_part = 0;
                budget = left.div_ceil((parts - part) as u64);
            }
            in_part += cost;
            left -= cost;
            row = rows.end;
            out.push(Band { pass, rows, part });
        }
    }
    out
}

/// The command buffer a generation is being recorded into: submission `used - 1` of
/// the slot's buffers, each between its two timestamps.
struct Parts<'a> {
    d: &'a ash::Device,
    queries: Option<vk::QueryPool>,
    q0: u32,
    cmds: &'a [vk::CommandBuffer],
    used: usize,
    cmd: vk::CommandBuffer,
}

impl Parts<'_> {
    /// The buffer of submission `part`, closing the ones before it.
    fn at(&mut self, part: usize) -> VkResult<vk::CommandBuffer> {
        while self.used <= part {
            // SAFETY: `cmd` is recording; the next buffer of this slot is idle (the
            // slot's previous generation has completed, see `record`).
            unsafe {
                let q = self.q0 + 2 * self.used as u32;
                if let Some(pool) = self.queries {
                    self.d.cmd_write_timestamp2(self.cmd, vk::PipelineStageFlags2::BOTTOM_OF_PIPE, pool, q - 1);
                }
                self.d.end_command_buffer(self.cmd).vk("vkEndCommandBuffer")?;
                self.cmd = self.cmds[self.used];
                begin_one_time(self.d, self.cmd)?;
                if let Some(pool) = self.queries {
                    self.d.cmd_write_timestamp2(self.cmd, vk::PipelineStageFlags2::TOP_OF_PIPE, pool, q);
                }
            }
            self.used += 1;
        }
        Ok(self.cmd)
    }
}
/// Timestamp queries per slot: a pair per submission.
pub(crate) const QUERIES_PER_SLOT: u32 = 2 * MAX_PARTS as u32;

/// Everything the errors thread owns on the GPU.
pub(crate) struct ErrorsGpu {
    pub(crate) device: Arc<Device>,
    terrain: Arc<TerrainGpu>,
    hf: Arc<Heightfield>,
    layout: BlockLayout,
    slots: Vec<Slot>,
    /// Two timestamps per submission of a generation, per slot (None: no timestamps, or
    /// not asked for).
    pub(crate) queries: Option<QueryPool>,
    /// Per slot: the slot's timestamps copied on the GPU (read after the generation
    /// finished, without vkGetQueryPoolResults, which waits for the queue on lavapipe).
    pub(crate) timestamps: Vec<Buffer>,
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

/// Copy regions for every mip of an R32F image, packed one after another from `offset`
/// (mip 0 first, rows tightly packed): the block-error layout of the README.
pub(crate) fn mip_copy_regions(image: &Image, offset: u64) -> Vec<vk::BufferImageCopy> {
    let mut at = offset;
    (0..image.mip_levels)
        .map(|mip| {
            let (width, height) = ((image.extent.width >> mip).max(1), (image.extent.height >> mip).max(1));
            let region = vk::BufferImageCopy::default()
                .buffer_offset(at)
                .image_subresource(vk::ImageSubresourceLayers {
                    aspect_mask: vk::ImageAspectFlags::COLOR,
                    mip_level: mip,
                    base_array_layer: 0,
                    layer_count: 1,
                })
                .image_extent(vk::Extent3D { width, height, depth: 1 });
            at += width as u64 * height as u64 * 4;
            region
        })
        .collect()
}

pub(crate) fn readback_bytes(layout: &BlockLayout) -> u64 {
    // Header and trailer words hold the generation number (torn-read check).
    (BlockErrors::packed_len(layout.root_lod(), layout.roots) * 4 + 8) as u64
}

impl ErrorsGpu {
    pub(crate) fn new(
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
        let desc = |fs, l| GraphicsPipelineDesc::fullscreen_pass(shaders::PASS_VERT, fs, GIE_FORMAT, l);
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
        crate::gpu::terrain::upload(device, &upload_pool, &dummy, &[&0f32.to_le_bytes()])?;

        // Mip i - 1 holds the groups of LOD i: roots << (n - i) along x and z.
        let [gie_w, gie_h] = hf.cells(1).map(|c| c as u32);
        let mut slots = Vec::new();
        for s in 0..2 {
            let gie = Image::new(
                device,
                &format!("GIE pyramid {s}"),
                vk::Extent2D { width: gie_w, height: gie_h },
                GIE_FORMAT,
                n,
                usage_rt,
                false,
            )?;
            let gie_mips = (0..n).map(|m| gie.mip_view(m, 1)).collect::<VkResult<Vec<_>>>()?;
            let (tbe, tbe_mips) = if root > 0 {
                let [w, h] = block_layout.blocks(1).map(|c| c as u32);
                let img = Image::new(
                    device,
                    &format!("block errors {s}"),
                    vk::Extent2D { width: w, height: h },
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
            let cmds = (0..MAX_PARTS).map(|_| commands.allocate()).collect::<VkResult<Vec<_>>>()?;
            slots.push(Slot { gie, gie_mips, tbe, tbe_mips, gie_sets, reduce_set, cmds });
        }
        Ok(ErrorsGpu {
            device: device.clone(),
            terrain,
            hf,
            layout: block_layout,
            slots,
            queries: None,
            timestamps: Vec::new(),
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

    /// The same, with timestamp queries for the GPU time of each generation, when the
    /// device has them.
    pub(crate) fn with_timestamps(mut self) -> VkResult<Self> {
        let queries = QueryPool::timestamps(&self.device, 2 * QUERIES_PER_SLOT)?;
        if queries.is_none() {
            tracing::info!("no timestamp queries on this device: error update GPU times are not reported");
        }
        let timestamps = match queries {
            Some(_) => (0..2)
                .map(|i| {
                    Buffer::new(
                        &self.device,
                        &format!("error timestamps {i}"),
                        QUERIES_PER_SLOT as u64 * 8,
                        vk::BufferUsageFlags::TRANSFER_DST,
                        gpu_allocator::MemoryLocation::GpuToCpu,
                    )
                })
                .collect::<VkResult<Vec<_>>>()?,
            None => Vec::new(),
        };
        self.queries = queries;
        self.timestamps = timestamps;
        Ok(self)
    }

    /// Draws one full-target triangle into `view` (a `side` x `side` mip), shading only
    /// the rows `rows` (a band of a pass split over several submissions).
    #[allow(clippy::too_many_arguments)]
    fn pass(
        &self,
        cmd: vk::CommandBuffer,
        view: vk::ImageView,
        [width, height]: [u32; 2],
        rows: std::ops::Range<u32>,
        (pipeline, pl): (&GraphicsPipeline, &PipelineLayout),
        set: vk::DescriptorSet,
        push: &[u8],
    ) {
        let d = &self.device.raw;
        let area = vk::Rect2D {
            offset: vk::Offset2D { x: 0, y: rows.start as i32 },
            extent: vk::Extent2D { width, height: rows.end - rows.start },
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
                    width: width as f32,
                    height: height as f32,
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

    /// Records generation `g` into its slot's command buffers: the GIE passes and the
    /// reduction split in row bands over `parts` of them (at most [`MAX_PARTS`]), the
    /// readback and timestamps in the last. Returns the buffers to submit, in order.
    pub(crate) fn record(
        &self,
        slot_index: usize,
        g: u64,
        p: &ErrorParams,
        readback: &Buffer,
        gie_dump: Option<&Buffer>,
        parts: usize,
    ) -> VkResult<Vec<vk::CommandBuffer>> {
        let slot = &self.slots[slot_index];
        let d = &self.device.raw;
        let queries = self.queries.as_ref().map(|q| q.handle);
        let cmd = slot.cmds[0];
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
        if let Some(pool) = queries {
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
        let gie_pipeline = &self.gie_pipelines[(p.mode == crate::lod::gie::ErrorMode::Strict) as usize];
        // About equal costs per submission; one pass may span several. The GIE passes
        // (one per LOD), then the reduction's (one per block LOD, when there is one).
        let weight = reduce_weight(self.layout.k() as usize);
        let parts = parts.clamp(1, MAX_PARTS);
        let mut sizes: Vec<PassSize> = (1..=n)
            .map(|lod| {
                let [width, height] = self.hf.cells(lod).map(|c| c as u32);
                PassSize { width, height, cost: 1 }
            })
            .collect();
        if slot.tbe.is_some() {
            sizes.extend((1..=root).map(|j| {
                let [width, height] = self.layout.blocks(j).map(|c| c as u32);
                PassSize { width, height, cost: weight }
            }));
        }
        let bands = split_passes(&sizes, parts);
        let mut recording = Parts { d, queries, q0, cmds: &slot.cmds[..parts], used: 1, cmd };
        let mut bands = bands.iter().peekable();
        for lod in 1..=n {
            let [side, groups_z] = self.hf.cells(lod).map(|c| c as u32);
            let push = GiePush {
                level: [lod as i32, n as i32, 0, unorm],
                extent: [self.hf.width as i32, self.hf.height as i32, side as i32, groups_z as i32],
                camera: [p.camera.x, p.camera.y, p.camera.z, p.kappa],
                params: [self.hf.spacing.x, self.hf.height_scale, p.near, self.hf.spacing.z],
            };
            while let Some(band) = bands.next_if(|b| b.pass == (lod - 1) as usize) {
                self.pass(
                    recording.at(band.part)?,
                    slot.gie_mips[(lod - 1) as usize].handle,
                    [side, groups_z],
                    band.rows.clone(),
                    (gie_pipeline, &self.gie_layout),
                    slot.gie_sets[(lod - 1) as usize],
                    bytemuck::bytes_of(&push),
                );
            }
            self.barrier(recording.cmd, &slot.gie, lod - 1, 1, (color, write, rt), (frag, read, ro));
        }
        let data_bytes = BlockErrors::packed_len(root, self.layout.roots) as u64 * 4;
        if let Some(tbe) = &slot.tbe {
            self.barrier(
                recording.cmd,
                tbe,
                0,
                root,
                (copy | color, write, vk::ImageLayout::UNDEFINED),
                (color, write, rt),
            );
            for j in 1..=root {
                let push = ReducePush { level: [j as i32, j as i32 - 1, (self.layout.k() - 1) as i32, 0] };
                let [w, h] = self.layout.blocks(j).map(|c| c as u32);
                // Each level reads only the GIE image, finished above: no barrier between
                // levels, and a level may span submissions like a GIE pass.
                while let Some(band) = bands.next_if(|b| b.pass == (n + j - 1) as usize) {
                    self.pass(
                        recording.at(band.part)?,
                        slot.tbe_mips[(j - 1) as usize].handle,
                        [w, h],
                        band.rows.clone(),
                        (&self.reduce_pipeline, &self.reduce_layout),
                        slot.reduce_set,
                        bytemuck::bytes_of(&push),
                    );
                }
            }
            self.barrier(
                recording.cmd,
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
                    recording.cmd,
                    tbe.handle,
                    vk::ImageLayout::TRANSFER_SRC_OPTIMAL,
                    readback.handle,
                    &regions,
                )
            };
        }
        debug_assert!(bands.next().is_none(), "every band recorded");
        let (cmd, used) = (recording.cmd, recording.used);
        if let Some(dump) = gie_dump {
            // Tests compare every GIE texel with the reference: copy all mips, LOD 1 first.
            self.barrier(
                recording.cmd,
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
                    recording.cmd,
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
            if let Some(pool) = queries {
                let last = q0 + 2 * used as u32 - 1;
                d.cmd_write_timestamp2(cmd, vk::PipelineStageFlags2::BOTTOM_OF_PIPE, pool, last);
                if let Some(buffer) = self.timestamps.get(slot_index).map(|b| b.handle) {
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
    let roots = hf.roots;
    let cells: Vec<usize> = (1..=n).map(|i| hf.cells(i).iter().product()).collect();
    let gpu = ErrorsGpu::new(device, terrain, hf, block_layout)?;
    let readback = Buffer::new(
        device,
        "block-error readback",
        readback_bytes(&block_layout),
        vk::BufferUsageFlags::TRANSFER_DST,
        gpu_allocator::MemoryLocation::GpuToCpu,
    )?;
    let texels: u64 = cells.iter().sum::<usize>() as u64;
    let dump = Buffer::new(
        device,
        "GIE dump",
        texels * 4,
        vk::BufferUsageFlags::TRANSFER_DST,
        gpu_allocator::MemoryLocation::GpuToCpu,
    )?;
    let timeline = TimelineSemaphore::new(device, 0)?;
    let cmds: Vec<_> = gpu
        .record(1, 1, params, &readback, Some(&dump), MAX_PARTS)?
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
    for len in cells {
        levels.push(data[at..at + len].to_vec());
        at += len;
    }
    let rb = readback.mapped()?;
    let len = BlockErrors::packed_len(root, roots);
    let blocks: Vec<f32> = bytemuck::pod_collect_to_vec(&rb[4..4 + len * 4]);
    Ok((GroupErrors { n, roots, levels }, BlockErrors::from_packed(root, roots, &blocks)))
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Checks what `split_passes` promises: every row of every pass once, in order;
    /// parts in `0..parts`, never going down; no part above its share by more than its
    /// last band.
    fn check(passes: &[PassSize], parts: usize) -> Vec<Band> {
        let bands = split_passes(passes, parts);
        let mut next = (0, 0);
        for b in &bands {
            while next.0 < passes.len() && next.1 == passes[next.0].height {
                next = (next.0 + 1, 0);
            }
            assert_eq!((b.pass, b.rows.start), next, "bands in order, no row left out or repeated");
            assert!(b.rows.end > b.rows.start && b.rows.end <= passes[b.pass].height);
            next.1 = b.rows.end;
        }
        assert!(next.0 == passes.len() || (next.0 == passes.len() - 1 && next.1 == passes[next.0].height));
        assert!(bands.windows(2).all(|w| w[0].part <= w[1].part), "parts never go down");
        assert!(bands.iter().all(|b| b.part < parts.max(1)));
        let cost =
            |b: &Band| u64::from(b.rows.end - b.rows.start) * u64::from(passes[b.pass].width) * passes[b.pass].cost;
        let total: u64 = bands.iter().map(cost).sum();
        let share = total.div_ceil(parts.max(1) as u64);
        for part in 0..parts {
            let of: Vec<&Band> = bands.iter().filter(|b| b.part == part).collect();
            let sum: u64 = of.iter().map(|b| cost(b)).sum();
            let last = of.last().map_or(0, |b| cost(b));
            let widest_row = passes.iter().map(|p| u64::from(p.width) * p.cost).max().unwrap_or(0);
            if parts > 1 {
                assert!(last <= (share / 4).max(1).max(widest_row), "band of {last} against a share of {share}");
            }
            assert!(sum <= share + share / 2 + widest_row, "part {part}: {sum} against a share of {share}");
        }
        bands
    }

    /// The largest part's cost over an equal share.
    fn worst_part(passes: &[PassSize], bands: &[Band], parts: usize) -> f64 {
        let cost =
            |b: &Band| u64::from(b.rows.end - b.rows.start) * u64::from(passes[b.pass].width) * passes[b.pass].cost;
        let total: u64 = bands.iter().map(cost).sum();
        let most = (0..parts).map(|p| bands.iter().filter(|b| b.part == p).map(cost).sum::<u64>()).max().unwrap();
        most as f64 / (total as f64 / parts as f64)
    }

    #[test]
    fn a_generation_splits_into_parts_of_about_equal_cost() {
        // The 4k flyover's shape: GIE passes from 2048 x 2048 down, then a reduction
        // whose fragments cost 256 each, on 64 x 64 blocks down.
        let mut passes: Vec<PassSize> =
            (1..=12).map(|l| PassSize { width: 4096 >> l, height: 4096 >> l, cost: 1 }).collect();
        passes.extend((1..=6).map(|j| PassSize { width: 128 >> j, height: 128 >> j, cost: 256 }));
        for parts in [1, 2, 3, 4, 7, 12, 16] {
            let bands = check(&passes, parts);
            let used = bands.iter().map(|b| b.part).max().unwrap() + 1;
            assert!(used == parts, "{parts} parts asked, {used} used");
            let worst = worst_part(&passes, &bands, parts);
            assert!(worst <= 1.3, "{parts} parts: the largest is {worst:.2} of a share");
        }
        // One part: every pass whole, in one submission.
        assert!(split_passes(&passes, 1).iter().all(|b| b.part == 0 && b.rows == (0..passes[b.pass].height)));
        // The reduction is split too: with 16 parts it does not sit in the last one whole.
        let bands = split_passes(&passes, 16);
        let reduce_parts: std::collections::BTreeSet<usize> =
            bands.iter().filter(|b| b.pass >= 12).map(|b| b.part).collect();
        assert!(reduce_parts.len() > 1, "the reduction spans parts: {reduce_parts:?}");
    }

    #[test]
    fn odd_shapes_split_without_losing_rows() {
        let cases: [&[PassSize]; 4] = [
            &[PassSize { width: 1, height: 1, cost: 1 }],
            &[PassSize { width: 3, height: 0, cost: 1 }, PassSize { width: 5, height: 7, cost: 3 }],
            &[PassSize { width: 1000, height: 1, cost: 1000 }, PassSize { width: 1, height: 1000, cost: 1 }],
            &[PassSize { width: 7, height: 13, cost: 0 }, PassSize { width: 2, height: 2, cost: 1 }],
        ];
        for passes in cases {
            for parts in [0, 1, 2, 5, 16, 100] {
                check(passes, parts);
            }
        }
    }
}
