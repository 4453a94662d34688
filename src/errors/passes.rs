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
    /// A generation is recorded into up to [`CHUNKS`] command buffers, submitted one
    /// after another, so that draw submissions can run in between on a shared queue.
    cmds: Vec<vk::CommandBuffer>,
}

/// Submissions a generation is split into, at most (about equal fragment counts).
pub(crate) const CHUNKS: usize = 4;
/// Timestamp queries per slot: a pair per submission.
pub(crate) const QUERIES_PER_SLOT: u32 = 2 * CHUNKS as u32;

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

    /// Records generation `g` into its slot's command buffers: the GIE passes split in
    /// row bands over up to [`CHUNKS`] of them, the reduction, readback and timestamps in
    /// the last. Returns the buffers to submit, in order.
    pub(crate) fn record(
        &self,
        slot_index: usize,
        g: u64,
        p: &ErrorParams,
        readback: &Buffer,
        gie_dump: Option<&Buffer>,
    ) -> VkResult<Vec<vk::CommandBuffer>> {
        let slot = &self.slots[slot_index];
        let d = &self.device.raw;
        let queries = self.queries.as_ref().map(|q| q.handle);
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
        // About equal fragment counts per submission; one pass may span several.
        let total: u64 = (1..=n).map(|lod| self.hf.cells(lod).iter().product::<usize>() as u64).sum();
        let budget = total.div_ceil(CHUNKS as u64).max(1);
        let mut in_chunk = 0u64;
        for lod in 1..=n {
            let [side, groups_z] = self.hf.cells(lod).map(|c| c as u32);
            let push = GiePush {
                level: [lod as i32, n as i32, 0, unorm],
                extent: [self.hf.width as i32, self.hf.height as i32, side as i32, groups_z as i32],
                camera: [p.camera.x, p.camera.y, p.camera.z, p.kappa],
                params: [self.hf.spacing.x, self.hf.height_scale, p.near, self.hf.spacing.z],
            };
            let band = ((budget / side as u64).max(1) as u32).min(groups_z);
            let mut row = 0;
            while row < groups_z {
                let rows = row..(row + band).min(groups_z);
                let fragments = (rows.end - rows.start) as u64 * side as u64;
                if in_chunk > 0 && in_chunk + fragments > budget && used < slot.cmds.len() {
                    // SAFETY: `cmd` is recording; the next buffer of this slot is idle
                    // (same argument as for the first).
                    unsafe {
                        let q = q0 + 2 * used as u32;
                        if let Some(pool) = queries {
                            d.cmd_write_timestamp2(cmd, vk::PipelineStageFlags2::BOTTOM_OF_PIPE, pool, q - 1);
                        }
                        d.end_command_buffer(cmd).vk("vkEndCommandBuffer")?;
                        cmd = slot.cmds[used];
                        begin_one_time(d, cmd)?;
                        if let Some(pool) = queries {
                            d.cmd_write_timestamp2(cmd, vk::PipelineStageFlags2::TOP_OF_PIPE, pool, q);
                        }
                    }
                    used += 1;
                    in_chunk = 0;
                }
                self.pass(
                    cmd,
                    slot.gie_mips[(lod - 1) as usize].handle,
                    [side, groups_z],
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
        let data_bytes = BlockErrors::packed_len(root, self.layout.roots) as u64 * 4;
        if let Some(tbe) = &slot.tbe {
            self.barrier(cmd, tbe, 0, root, (copy | color, write, vk::ImageLayout::UNDEFINED), (color, write, rt));
            for j in 1..=root {
                let push = ReducePush { level: [j as i32, j as i32 - 1, (self.layout.k() - 1) as i32, 0] };
                let [w, h] = self.layout.blocks(j).map(|c| c as u32);
                self.pass(
                    cmd,
                    slot.tbe_mips[(j - 1) as usize].handle,
                    [w, h],
                    0..h,
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
    for len in cells {
        levels.push(data[at..at + len].to_vec());
        at += len;
    }
    let rb = readback.mapped()?;
    let len = BlockErrors::packed_len(root, roots);
    let blocks: Vec<f32> = bytemuck::pod_collect_to_vec(&rb[4..4 + len * 4]);
    Ok((GroupErrors { n, roots, levels }, BlockErrors::from_packed(root, roots, &blocks)))
}
