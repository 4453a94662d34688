//! The errors activity's passes over the atlas (SPEC 4 and 8, "Residency"): per
//! generation, one fragment pass a tile shades the errors of its blocks
//! (`glsl/tile_errors.frag`: every group's `D * height_scale * kappa / distance`, the
//! largest a block; in the paper's mode `glsl/tile_paper.frag`, the blocks one LOD
//! coarser, from their dropped vertices) into its cell of an R32F target, and only the
//! cells shaded are copied to a host-visible buffer, one after another: 4 bytes a block,
//! 256 a tile. Owned and recorded by the errors thread ([`crate::errors::atlas`]). Two
//! slots of target, readback buffer and timestamps are used in turn, generation `g` in
//! slot `g % 2`: with two generations in flight (`--error-pacing free`) each writes its
//! own, and the thread reads a slot back before the generation after next reuses it.
//!
//! Why one fragment a block, not one a group then a reduction as in memory: a group
//! image over the atlas would take 256 KB a tile shaded (R32F, 256 x 256 groups), as much
//! again as the tile's heights and deviations; the block's maximum is taken in the
//! fragment that computes its groups' errors instead.

use crate::errors::handoff::Handoff;
use crate::gpu::layout::{self as layout, TileErrorsPush};
use crate::gpu::shaders;
use crate::lod::camera::Camera;
use crate::lod::gie::ErrorMode;
use crate::stream::errors::{paper_offset, paper_steps};
use crate::stream::{Grid, TileKey};
use crate::vk::{
    host_read_barrier, image_barrier, vk, Buffer, DescriptorPool, DescriptorSetLayout, Device, FrameTimer,
    GraphicsPipeline, GraphicsPipelineDesc, Image, ImageUse, PipelineLayout, Sampler, VkResult, COPY_SOURCE,
};
use std::sync::Arc;

/// Cells of the target along x and y: one a tile shaded, as many as the atlas has layers
/// at most ([`super::atlas::MAX_LAYERS`]).
const CELLS: [u32; 2] = [64, 32];

/// The first texel of the `i`-th tile's cell (`n` blocks a side), row by row.
fn cell_of(i: usize, n: u32) -> [u32; 2] {
    [(i as u32 % CELLS[0]) * n, (i as u32 / CELLS[0]) * n]
}

const WRITTEN: ImageUse = (
    vk::PipelineStageFlags2::COLOR_ATTACHMENT_OUTPUT,
    vk::AccessFlags2::COLOR_ATTACHMENT_WRITE,
    vk::ImageLayout::COLOR_ATTACHMENT_OPTIMAL,
);

/// A tile and its blocks' errors, row-major.
pub(crate) type TileBlocks = (TileKey, Vec<f32>);

/// What one generation shaded.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct Shaded {
    pub tiles: u64,
    pub groups: u64,
    pub bytes_read_back: u64,
    /// Its GPU time, when the device has timestamps.
    pub gpu_ms: Option<f64>,
}

/// One generation's target, readback buffer and timestamps.
struct Slot {
    target: Image,
    readback: Buffer,
    timer: Option<FrameTimer>,
}

pub(crate) struct AtlasPasses {
    device: Arc<Device>,
    /// Strict mode's pass (`tile_errors.frag`) and the paper's (`tile_paper.frag`).
    pipeline: GraphicsPipeline,
    paper: GraphicsPipeline,
    layout: PipelineLayout,
    _set_layout: DescriptorSetLayout,
    _pool: DescriptorPool,
    set: vk::DescriptorSet,
    _sampler: Sampler,
    slots: [Slot; 2],
    /// Blocks a tile side (`tile_quads / block_quads`): a cell's side in texels.
    per_side: u32,
}

impl AtlasPasses {
    /// The passes over `heights` and `deviation` (the atlas's two array images, one tile
    /// a layer) for tiles of `grid`.
    pub(crate) fn new(device: &Arc<Device>, grid: &Grid, heights: &Image, deviation: &Image) -> VkResult<Self> {
        let frag = vk::ShaderStageFlags::FRAGMENT;
        let sampled = vk::DescriptorType::COMBINED_IMAGE_SAMPLER;
        let set_layout = DescriptorSetLayout::new(
            device,
            &[
                (layout::TILE_ERRORS_BINDING_HEIGHTS, sampled, frag),
                (layout::TILE_ERRORS_BINDING_DEVIATION, sampled, frag),
            ],
        )?;
        let pl = PipelineLayout::new(device, &set_layout, std::mem::size_of::<TileErrorsPush>() as u32, frag)?;
        let pass = |frag| {
            GraphicsPipeline::new(
                device,
                &GraphicsPipelineDesc::fullscreen_pass(shaders::PASS_VERT, frag, vk::Format::R32_SFLOAT, &pl),
            )
        };
        let (pipeline, paper) = (pass(shaders::TILE_ERRORS_FRAG)?, pass(shaders::TILE_PAPER_FRAG)?);
        let pool = DescriptorPool::new(device, 1, &[(sampled, 2)])?;
        let set = pool.allocate(&set_layout)?;
        let sampler = Sampler::new(device, vk::Filter::NEAREST, vk::SamplerAddressMode::CLAMP_TO_EDGE)?;
        pool.write(
            set,
            &[
                (layout::TILE_ERRORS_BINDING_HEIGHTS, heights.view, sampler.handle),
                (layout::TILE_ERRORS_BINDING_DEVIATION, deviation.view, sampler.handle),
            ],
            &[],
        );
        let per_side = (grid.tile_quads / grid.block_quads) as u32;
        let extent = vk::Extent2D { width: CELLS[0] * per_side, height: CELLS[1] * per_side };
        let usage = vk::ImageUsageFlags::COLOR_ATTACHMENT | vk::ImageUsageFlags::TRANSFER_SRC;
        let slot = |i: usize| -> VkResult<Slot> {
            let name = format!("block errors over the atlas {i}");
            let target = Image::new(device, &name, extent, vk::Format::R32_SFLOAT, 1, usage, false)?;
            let readback = Buffer::new(
                device,
                &format!("block errors readback {i}"),
                u64::from(extent.width) * u64::from(extent.height) * 4,
                vk::BufferUsageFlags::TRANSFER_DST,
                gpu_allocator::MemoryLocation::GpuToCpu,
            )?;
            Ok(Slot { target, readback, timer: FrameTimer::new(device)? })
        };
        let slots = [slot(0)?, slot(1)?];
        Ok(AtlasPasses {
            device: device.clone(),
            pipeline,
            paper,
            layout: pl,
            _set_layout: set_layout,
            _pool: pool,
            set,
            _sampler: sampler,
            slots,
            per_side,
        })
    }

    /// The most tiles one generation shades.
    pub(crate) fn capacity() -> usize {
        (CELLS[0] * CELLS[1]) as usize
    }

    /// Texels a side of a tile's cell that `mode` reads back: strict mode, one a block of
    /// the tile's own level; the paper's, the whole cell ([`Self::passes_of`]).
    fn shaded_side(&self, _mode: ErrorMode) -> u32 {
        self.per_side
    }

    /// The draws that shade tile `key` (of a grid whose top level is `top`) in `mode`:
    /// where in its cell along x, blocks a side, and the push constants' `tile.w`. Strict
    /// mode: the blocks of the tile's own level, its slot of deviations. The paper's: the
    /// blocks `k` LODs coarser, `k` from 1 ([`paper_steps`], [`paper_offset`]).
    fn passes_of(&self, key: TileKey, slot: u32, top: u8, mode: ErrorMode) -> Vec<(u32, u32, i32)> {
        let n = self.per_side;
        match mode {
            ErrorMode::Strict => vec![(0, n, slot as i32)],
            ErrorMode::Paper => (1..=paper_steps(key, top, n as usize))
                .map(|k| (paper_offset(n as usize, k) as u32, n >> k, k as i32))
                .collect(),
        }
    }

    /// Records the shading of `tiles` (each with its layer of heights and its slot of
    /// deviations, at most [`Self::capacity`]) in `mode` as generation `g` (into slot
    /// `g % 2`, whose last generation the caller has read back)
    /// for the camera `cam`, relative to sample `anchor`, into `cmd` (recording), and the
    /// copy of their cells to the readback buffer.
    pub(crate) fn record(
        &self,
        g: u64,
        cmd: vk::CommandBuffer,
        grid: &Grid,
        tiles: &[(TileKey, u32, u32)],
        (anchor, cam): ([i64; 2], &Camera),
        (unorm16, mode): (bool, ErrorMode),
    ) {
        assert!(!tiles.is_empty() && tiles.len() <= Self::capacity(), "{} tiles to shade", tiles.len());
        let d = &self.device.raw;
        let n = self.per_side;
        // The texels of a cell shaded and read back: its first `m x m`.
        let m = self.shaded_side(mode);
        let pipeline = if mode == ErrorMode::Paper { &self.paper } else { &self.pipeline };
        let rows = (tiles.len() as u32).div_ceil(CELLS[0]) * n;
        let Slot { target, readback, timer } = &self.slots[Handoff::slot(g)];
        let width = target.extent.width;
        let area = vk::Rect2D { offset: vk::Offset2D::default(), extent: vk::Extent2D { width, height: rows } };
        let att = [vk::RenderingAttachmentInfo::default()
            .image_view(target.view)
            .image_layout(vk::ImageLayout::COLOR_ATTACHMENT_OPTIMAL)
            .load_op(vk::AttachmentLoadOp::DONT_CARE)
            .store_op(vk::AttachmentStoreOp::STORE)];
        let info = vk::RenderingInfo::default().render_area(area).layer_count(1).color_attachments(&att);
        let range = target.range(0, 1);
        let discarded = (vk::PipelineStageFlags2::COPY, vk::AccessFlags2::NONE, vk::ImageLayout::UNDEFINED);
        // SAFETY: `cmd` is recording on the errors thread, which has read back the slot's
        // last generation before recording this one (so its target and readback are idle);
        // every object outlives the submission; each cell lies inside the target.
        unsafe {
            if let Some(t) = timer {
                t.begin(d, cmd);
            }
            image_barrier(d, cmd, target.handle, range, discarded, WRITTEN);
            d.cmd_begin_rendering(cmd, &info);
            d.cmd_bind_pipeline(cmd, vk::PipelineBindPoint::GRAPHICS, pipeline.handle);
            d.cmd_bind_descriptor_sets(cmd, vk::PipelineBindPoint::GRAPHICS, self.layout.handle, 0, &[self.set], &[]);
            for (i, &(key, layer, slot)) in tiles.iter().enumerate() {
                let cell = cell_of(i, n);
                let span = grid.tile_span(key.level) as i64;
                for (offset, side, w) in self.passes_of(key, slot, grid.top, mode) {
                    let at = [cell[0] + offset, cell[1]];
                    let push = TileErrorsPush {
                        tile: [layer as i32, i32::from(key.level), i32::from(unorm16), w],
                        origin: [
                            (i64::from(key.tx) * span - anchor[0]) as i32,
                            (i64::from(key.tz) * span - anchor[1]) as i32,
                            at[0] as i32,
                            at[1] as i32,
                        ],
                        camera: [cam.position.x, cam.position.y, cam.position.z, cam.kappa()],
                        params: [grid.spacing[0] as f32, grid.height_scale as f32, cam.near, grid.spacing[1] as f32],
                        shape: [grid.block_quads as i32, 0, 0, 0],
                    };
                    let rect = vk::Rect2D {
                        offset: vk::Offset2D { x: at[0] as i32, y: at[1] as i32 },
                        extent: vk::Extent2D { width: side, height: side },
                    };
                    let viewport = vk::Viewport {
                        x: at[0] as f32,
                        y: at[1] as f32,
                        width: side as f32,
                        height: side as f32,
                        min_depth: 0.0,
                        max_depth: 1.0,
                    };
                    d.cmd_set_viewport(cmd, 0, &[viewport]);
                    d.cmd_set_scissor(cmd, 0, &[rect]);
                    d.cmd_push_constants(
                        cmd,
                        self.layout.handle,
                        vk::ShaderStageFlags::FRAGMENT,
                        0,
                        bytemuck::bytes_of(&push),
                    );
                    d.cmd_draw(cmd, 3, 1, 0, 0);
                }
            }
            d.cmd_end_rendering(cmd);
            image_barrier(d, cmd, target.handle, range, WRITTEN, COPY_SOURCE);
            // The cells shaded and nothing else, one after another: 4 bytes a block.
            let regions: Vec<vk::BufferImageCopy> = (0..tiles.len())
                .map(|i| {
                    let cell = cell_of(i, n);
                    vk::BufferImageCopy::default()
                        .buffer_offset((i as u32 * m * m * 4) as u64)
                        .image_subresource(vk::ImageSubresourceLayers {
                            aspect_mask: vk::ImageAspectFlags::COLOR,
                            mip_level: 0,
                            base_array_layer: 0,
                            layer_count: 1,
                        })
                        .image_offset(vk::Offset3D { x: cell[0] as i32, y: cell[1] as i32, z: 0 })
                        .image_extent(vk::Extent3D { width: m, height: m, depth: 1 })
                })
                .collect();
            let src = vk::ImageLayout::TRANSFER_SRC_OPTIMAL;
            d.cmd_copy_image_to_buffer(cmd, target.handle, src, readback.handle, &regions);
            let written = (vk::PipelineStageFlags2::COPY, vk::AccessFlags2::TRANSFER_WRITE);
            host_read_barrier(d, cmd, readback.handle, written);
            if let Some(t) = timer {
                t.end(d, cmd);
            }
        }
    }

    /// The block errors of `tiles` (as recorded in `mode` for generation `g`), once `g`
    /// has finished: per tile, its cell row-major; and what the generation shaded.
    pub(crate) fn read(
        &self,
        g: u64,
        grid: &Grid,
        tiles: &[(TileKey, u32, u32)],
        mode: ErrorMode,
    ) -> VkResult<(Vec<TileBlocks>, Shaded)> {
        let m = self.shaded_side(mode) as usize;
        let cell = m * m;
        let Slot { readback, timer, .. } = &self.slots[Handoff::slot(g)];
        let bytes = readback.mapped()?;
        let out = tiles
            .iter()
            .enumerate()
            .map(|(i, &(key, _, _))| {
                let at = &bytes[i * cell * 4..(i + 1) * cell * 4];
                (key, at.chunks_exact(4).map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]])).collect())
            })
            .collect();
        let gpu_ms = timer.as_ref().map(|t| t.read().map(|r| r.1)).transpose()?;
        // block_quads^2 groups a block shaded.
        let blocks: u32 = tiles
            .iter()
            .flat_map(|&(key, _, slot)| self.passes_of(key, slot, grid.top, mode))
            .map(|(_, side, _)| side * side)
            .sum();
        let shaded = Shaded {
            tiles: tiles.len() as u64,
            groups: u64::from(blocks) * (grid.block_quads * grid.block_quads) as u64,
            bytes_read_back: (tiles.len() * cell * 4) as u64,
            gpu_ms,
        };
        Ok((out, shaded))
    }
}
