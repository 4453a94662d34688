//! The lighting map on the GPU: `glsl/lighting.frag` drawn over an RG8 image (sun
//! visibility, ambient occlusion), at load and whenever the sun moves. The terrain
//! shader samples it; `crate::draw::lighting` is its CPU reference.

use crate::draw::lighting::{LightingSource, Sun, MAX_LIGHTING_SIDE};
use crate::gpu::layout::{self as layout, LightingPush};
use crate::gpu::shaders;
use crate::gpu::terrain::TerrainGpu;
use crate::lod::heightfield::{HeightFormat, Heightfield};
use crate::vk::{
    image_barrier, vk, Buffer, CommandPool, DescriptorPool, DescriptorSetLayout, Device, GraphicsPipeline,
    GraphicsPipelineDesc, Image, PipelineLayout, Sampler, VkResult, COPY_SOURCE, FRAGMENT_SAMPLED,
};
use std::sync::Arc;

pub const LIGHTING_FORMAT: vk::Format = vk::Format::R8G8_UNORM;

pub struct LightingMap {
    pub image: Image,
    /// Linear filtering, clamped: the terrain shader reads between texels.
    pub sampler: Sampler,
    pipeline: GraphicsPipeline,
    layout: PipelineLayout,
    set: vk::DescriptorSet,
    _pool: DescriptorPool,
    _set_layout: DescriptorSetLayout,
    commands: CommandPool,
    sun: Option<Sun>,
    max_side: usize,
    /// Wall time of the last redraw (ms).
    last_ms: f64,
    device: Arc<Device>,
}

impl LightingMap {
    /// The map of `terrain` (the heightfield `hf` on the GPU) for `sun` (`None`: all lit).
    pub fn new(device: &Arc<Device>, hf: &Heightfield, terrain: &TerrainGpu, sun: Option<Sun>) -> VkResult<Self> {
        Self::with_max_side(device, hf, terrain, sun, MAX_LIGHTING_SIDE)
    }

    /// As [`Self::new`] with at most `max_side` texels a side (tests of small maps).
    pub fn with_max_side(
        device: &Arc<Device>,
        hf: &Heightfield,
        terrain: &TerrainGpu,
        sun: Option<Sun>,
        max_side: usize,
    ) -> VkResult<Self> {
        let heights = (terrain.heights.view, terrain.nearest.handle);
        Self::of_source(device, &LightingSource::whole(hf), heights, sun, max_side)
    }

    /// The map made from `src`, whose heights the GPU reads through `heights` (an image
    /// view of `src.hf`'s grid and a nearest sampler, kept alive by the caller as long as
    /// the map).
    pub fn of_source(
        device: &Arc<Device>,
        src: &LightingSource,
        heights: (vk::ImageView, vk::Sampler),
        sun: Option<Sun>,
        max_side: usize,
    ) -> VkResult<Self> {
        let ([w, h], _) = src.size(max_side);
        let image = Image::new(
            device,
            "lighting map",
            vk::Extent2D { width: w as u32, height: h as u32 },
            LIGHTING_FORMAT,
            1,
            vk::ImageUsageFlags::COLOR_ATTACHMENT | vk::ImageUsageFlags::SAMPLED | vk::ImageUsageFlags::TRANSFER_SRC,
            false,
        )?;
        let frag = vk::ShaderStageFlags::FRAGMENT;
        let sampler_ty = vk::DescriptorType::COMBINED_IMAGE_SAMPLER;
        let set_layout = DescriptorSetLayout::new(device, &[(layout::LIGHTING_BINDING_HEIGHTS, sampler_ty, frag)])?;
        let pipeline_layout =
            PipelineLayout::new(device, &set_layout, std::mem::size_of::<LightingPush>() as u32, frag)?;
        let pipeline = GraphicsPipeline::new(
            device,
            &GraphicsPipelineDesc::fullscreen_pass(
                shaders::PASS_VERT,
                shaders::LIGHTING_FRAG,
                LIGHTING_FORMAT,
                &pipeline_layout,
            ),
        )?;
        let pool = DescriptorPool::new(device, 1, &[(sampler_ty, 1)])?;
        let set = pool.allocate(&set_layout)?;
        pool.write(set, &[(layout::LIGHTING_BINDING_HEIGHTS, heights.0, heights.1)], &[]);
        let mut map = LightingMap {
            image,
            sampler: Sampler::new(device, vk::Filter::LINEAR, vk::SamplerAddressMode::CLAMP_TO_EDGE)?,
            pipeline,
            layout: pipeline_layout,
            set,
            _pool: pool,
            _set_layout: set_layout,
            commands: CommandPool::new(device, device.draw_queue.family)?,
            sun: None,
            max_side,
            last_ms: 0.0,
            device: device.clone(),
        };
        map.draw(src, sun, true)?;
        Ok(map)
    }

    pub fn sun(&self) -> Option<Sun> {
        self.sun
    }

    /// Wall time of the last redraw, submission to completion (ms).
    pub fn last_ms(&self) -> f64 {
        self.last_ms
    }

    /// Redraws the map for `sun` on the draw queue and waits. Frames already submitted
    /// that sample the map finish first (the barrier below orders the rewrite after
    /// their fragment shaders); frames recorded after this call see the new map.
    pub fn set_sun(&mut self, src: &LightingSource, sun: Option<Sun>) -> VkResult<()> {
        if sun != self.sun {
            self.draw(src, sun, false)?;
        }
        Ok(())
    }

    /// Redraws the map for the same sun over `src` with a new height scale (the viewer's
    /// vertical exaggeration), as [`Self::set_sun`] does.
    pub fn redraw(&mut self, src: &LightingSource) -> VkResult<()> {
        self.draw(src, self.sun, false)
    }

    fn draw(&mut self, src: &LightingSource, sun: Option<Sun>, first: bool) -> VkResult<()> {
        let (hf, spacing) = (src.hf, src.spacing());
        let (d, tan, metres_per_step) = sun.map_or(([0.0; 2], 0.0, 1.0), |s| s.march(spacing));
        let push = LightingPush {
            sun: [d[0], tan, d[1], sun.is_some() as i32 as f32],
            grid: [
                src.extent[0] as i32,
                src.extent[1] as i32,
                src.size(self.max_side).1 as i32,
                (hf.format == HeightFormat::Unorm16) as i32,
            ],
            params: [spacing.x, hf.height_scale, spacing.z, metres_per_step],
            source: [src.stride as i32, 0, 0, 0],
        };
        let extent = self.image.extent;
        let raw = &self.device.raw;
        let image = self.image.handle;
        let range = self.image.range(0, 1);
        // Before the first draw nothing used the image; after, terrain fragment shaders did.
        let before = if first {
            (vk::PipelineStageFlags2::NONE, vk::AccessFlags2::NONE, vk::ImageLayout::UNDEFINED)
        } else {
            (
                vk::PipelineStageFlags2::FRAGMENT_SHADER,
                vk::AccessFlags2::SHADER_SAMPLED_READ,
                vk::ImageLayout::UNDEFINED,
            )
        };
        let target = (
            vk::PipelineStageFlags2::COLOR_ATTACHMENT_OUTPUT,
            vk::AccessFlags2::COLOR_ATTACHMENT_WRITE,
            vk::ImageLayout::COLOR_ATTACHMENT_OPTIMAL,
        );
        let sampled = FRAGMENT_SAMPLED;
        let started = std::time::Instant::now();
        self.device.one_shot(&self.commands, |cmd| {
            let att = [vk::RenderingAttachmentInfo::default()
                .image_view(self.image.view)
                .image_layout(vk::ImageLayout::COLOR_ATTACHMENT_OPTIMAL)
                .load_op(vk::AttachmentLoadOp::DONT_CARE)
                .store_op(vk::AttachmentStoreOp::STORE)];
            let area = vk::Rect2D { offset: vk::Offset2D::default(), extent };
            let rendering = vk::RenderingInfo::default().render_area(area).layer_count(1).color_attachments(&att);
            let viewport = vk::Viewport {
                width: extent.width as f32,
                height: extent.height as f32,
                max_depth: 1.0,
                ..Default::default()
            };
            // SAFETY: `cmd` is recording on this thread; every object outlives the wait in
            // one_shot; the barriers order the write after earlier reads and before later
            // ones.
            unsafe {
                image_barrier(raw, cmd, image, range, before, target);
                raw.cmd_begin_rendering(cmd, &rendering);
                raw.cmd_bind_pipeline(cmd, vk::PipelineBindPoint::GRAPHICS, self.pipeline.handle);
                raw.cmd_bind_descriptor_sets(
                    cmd,
                    vk::PipelineBindPoint::GRAPHICS,
                    self.layout.handle,
                    0,
                    &[self.set],
                    &[],
                );
                raw.cmd_push_constants(
                    cmd,
                    self.layout.handle,
                    vk::ShaderStageFlags::FRAGMENT,
                    0,
                    bytemuck::bytes_of(&push),
                );
                raw.cmd_set_viewport(cmd, 0, &[viewport]);
                raw.cmd_set_scissor(cmd, 0, &[area]);
                raw.cmd_draw(cmd, 3, 1, 0, 0);
                raw.cmd_end_rendering(cmd);
                image_barrier(raw, cmd, image, range, target, sampled);
            }
        })?;
        self.last_ms = started.elapsed().as_secs_f64() * 1e3;
        if sun.is_some() {
            tracing::info!("lighting map {}x{} for sun {sun:?}: {:.0} ms", extent.width, extent.height, self.last_ms);
        }
        self.sun = sun;
        Ok(())
    }

    /// The map read back to the host, row-major RG8 (tests).
    pub fn read(&self) -> VkResult<Vec<[u8; 2]>> {
        let extent = self.image.extent;
        let bytes = extent.width as u64 * extent.height as u64 * 2;
        let buffer = Buffer::new(
            &self.device,
            "lighting readback",
            bytes,
            vk::BufferUsageFlags::TRANSFER_DST,
            gpu_allocator::MemoryLocation::GpuToCpu,
        )?;
        let raw = &self.device.raw;
        let (image, range) = (self.image.handle, self.image.range(0, 1));
        let sampled = FRAGMENT_SAMPLED;
        let source = COPY_SOURCE;
        self.device.one_shot(&self.commands, |cmd| {
            // SAFETY: as in `draw`; the buffer (two bytes a texel) outlives the wait.
            unsafe {
                image_barrier(raw, cmd, image, range, sampled, source);
                crate::vk::copy_image_to_host(raw, cmd, image, extent, buffer.handle);
                image_barrier(raw, cmd, image, range, source, sampled);
            }
        })?;
        Ok(bytemuck::pod_collect_to_vec(&buffer.mapped()?[..bytes as usize]))
    }
}

/// A lighting map made from heights it holds itself: every `stride`-th sample of a
/// terrain that is not in one image (streamed frames), uploaded once into an image of its
/// own on the draw queue's family; and the gradient map of those samples, which the
/// deferred pass shades from as memory does from its own (one gather a pixel instead of
/// five).
pub struct OwnLighting {
    /// First: its descriptor set reads `_heights` through `_nearest` at every redraw.
    pub map: LightingMap,
    _heights: Image,
    gradients: Image,
    /// [`Heightfield::gradient_map`]'s scale per unit of height scale (as
    /// [`crate::gpu::terrain::TerrainGpu::gradient_scale_per_unit`]: exaggeration keeps
    /// the map).
    gradient_scale_per_unit: f32,
    _nearest: Sampler,
    hf: Heightfield,
    stride: usize,
    extent: [usize; 2],
    /// Whether `hf` holds the terrain's heights (not [`Self::everything_lit`]'s).
    holds_heights: bool,
}

impl OwnLighting {
    /// The map of the terrain of `extent` samples whose every `stride`-th sample `hf`
    /// holds ([`LightingSource::every`]), for `sun`; water at world heights up to
    /// `sea_level` (at `hf`'s height scale).
    pub fn new(
        device: &Arc<Device>,
        hf: Heightfield,
        stride: usize,
        extent: [usize; 2],
        sun: Option<Sun>,
        sea_level: f32,
    ) -> VkResult<Self> {
        let pool = CommandPool::new(device, device.draw_queue.family)?;
        let (heights, _) = crate::gpu::terrain::heights_image(device, &pool, &hf, "lighting heights", false)?;
        let (gradients, scale) = crate::gpu::terrain::gradients_image(device, &pool, &hf, sea_level)?;
        let nearest = Sampler::new(device, vk::Filter::NEAREST, vk::SamplerAddressMode::CLAMP_TO_EDGE)?;
        let src = LightingSource::every(&hf, stride, extent);
        let map = LightingMap::of_source(device, &src, (heights.view, nearest.handle), sun, MAX_LIGHTING_SIDE)?;
        Ok(OwnLighting {
            map,
            _heights: heights,
            gradients,
            gradient_scale_per_unit: scale / hf.height_scale,
            _nearest: nearest,
            hf,
            stride,
            extent,
            holds_heights: true,
        })
    }

    /// A map that lights everything (no shadows, the whole sky open): for frames with
    /// no heights to make one from.
    pub fn everything_lit(device: &Arc<Device>) -> VkResult<Self> {
        let flat = Heightfield::embed("flat", 3, 3, &[0.0; 9], HeightFormat::Float32, 1.0, 1.0)
            .map_err(|e| crate::vk::VkError::Setup(e.to_string()))?;
        Ok(OwnLighting { holds_heights: false, ..Self::new(device, flat, 1, [3, 3], None, 0.0)? })
    }

    /// Whether the map was made from the terrain's heights, which
    /// [`Self::heights_view`] then shows (every `source().stride`-th sample).
    pub fn holds_heights(&self) -> bool {
        self.holds_heights
    }

    /// The gradient map of the held samples ([`Heightfield::gradient_map`], R32_UINT),
    /// read in SHADER_READ_ONLY_OPTIMAL.
    pub fn gradients_view(&self) -> vk::ImageView {
        self.gradients.view
    }

    /// The scale of [`Self::gradients_view`]'s units at the current height scale.
    pub fn gradient_scale(&self) -> f32 {
        self.gradient_scale_per_unit * self.hf.height_scale
    }

    pub fn source(&self) -> LightingSource<'_> {
        LightingSource::every(&self.hf, self.stride, self.extent)
    }

    /// Terrain samples per texel of the map.
    pub fn samples_per_texel(&self) -> usize {
        self.source().size(self.map.max_side).1
    }

    /// Redraws the map for `sun` ([`LightingMap::set_sun`]).
    pub fn set_sun(&mut self, sun: Option<Sun>) -> VkResult<()> {
        let src = LightingSource::every(&self.hf, self.stride, self.extent);
        self.map.set_sun(&src, sun)
    }

    /// Redraws the map with heights at `scale` world units per raw unit (the viewer's
    /// vertical exaggeration).
    pub fn set_height_scale(&mut self, scale: f32) -> VkResult<()> {
        if scale != self.hf.height_scale {
            self.hf.height_scale = scale;
            let src = LightingSource::every(&self.hf, self.stride, self.extent);
            self.map.redraw(&src)?;
        }
        Ok(())
    }
}
