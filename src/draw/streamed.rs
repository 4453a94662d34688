//! Streamed frames on the GPU (SPEC section 8): the blocks of a [`Selection`] drawn from
//! the heightfield atlas, each block's heights fetched from its tile's layer, every
//! position relative to the camera's nearest sample (`glsl/stream.vert`).
//!
//! Shading is the in-memory ramp, water, light, fog and sky; normals from the surface's
//! derivatives, or with `--shading heights` as in memory from the heights of the block's
//! tile (streamed tiles bring no gradient map); sun shadows and ambient occlusion from a
//! lighting map made as in memory from the tiles of a coarser level
//! ([`lighting_heights`]). Deferred by default, as in memory: the blocks write depth
//! only, then one pass shades each pixel once, its normal and sea share from the
//! gradient map of the lighting map's heights, or up close over a terrain held coarser
//! than its samples from the points drawn beside it (`glsl/stream_shade.frag`;
//! `--pixels forward`, the colour-by-LOD view and `--shading heights` shade every
//! fragment as it is drawn). Frames go offscreen (read back) or into a window's
//! swapchain image.
//!
//! [`Selection`]: crate::stream::traverse::Selection

use super::blocks::{
    attachment_barriers, begin_shading_pass, depth_pass_pipeline, depth_precise_at, draw_visible_parts, BlockMesh,
    NormalSource, PixelPass, Target, COLOR_FORMAT, COLOR_RANGE, DEPTH_FORMAT, SKY_HORIZON, SKY_ZENITH,
};
use crate::draw::lighting::{samples_per_texel, MAX_LIGHTING_SIDE};
use crate::draw::lighting_gpu::OwnLighting;
use crate::errors::atlas::HeightAtlas;
use crate::gpu::layout::{self, BlockPush, FrameUniforms};
use crate::gpu::shaders;
use crate::gpu::terrain::{Texture, TextureImages};
use crate::input::archive::{level_heightfield, LevelTerrain};
use crate::lod::block::{morph_value, BlockLayout, CORNER_UNRESOLVED};
use crate::lod::camera::Camera;
use crate::lod::heightfield::{HeightFormat, Heightfield, HeightfieldError};
use crate::stream::draw::StreamedBlock;
use crate::stream::io::TileSource;
use crate::stream::Grid;
use crate::stream::TileKey;
use crate::vk::{
    begin_one_time, image_barrier, vk, Buffer, CommandPool, DepthMode, DescriptorPool, DescriptorSetLayout, Device,
    Fence, FrameTimer, GraphicsPipeline, GraphicsPipelineDesc, Image, PipelineLayout, Sampler, VkError, VkResult,
    VkResultExt,
};
use std::sync::Arc;

/// What a streamed frame drew.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct StreamedStats {
    pub blocks: usize,
    /// Blocks left out because their tile had no atlas layer (counted over the bound by
    /// the caller; 0 when the atlas holds the frame's tiles).
    pub missing: usize,
    /// Parts of drawn blocks left out ([`DrawBlock::hidden_parts`]: outside the frustum).
    ///
    /// [`DrawBlock::hidden_parts`]: crate::lod::block::DrawBlock::hidden_parts
    pub hidden_parts: u64,
    /// Triangles drawn (the drawn blocks' less their hidden parts').
    pub triangles: u64,
    /// Indexed draws: one per run of visible parts of a block.
    pub draw_calls: u64,
    /// Shaded deferred (each pixel once) rather than forward.
    pub deferred: bool,
    /// Blocks drawn by rays (`--raycast`: only in deferred frames), and the pixels of
    /// their boxes, the rays cast (set by the caller that chose them).
    pub raycast_blocks: u64,
    pub raycast_pixels: f64,
    /// The frame's GPU time, when the queue has timestamps.
    pub gpu_ms: Option<f64>,
}

pub struct StreamedRenderer {
    device: Arc<Device>,
    layout: BlockLayout,
    frame: u64,
    cmd: vk::CommandBuffer,
    fence: Fence,
    /// The frame's timestamps (none where the queue has no timestamp bits).
    timer: Option<FrameTimer>,
    commands: CommandPool,
    /// The pipelines for each colour format drawn to (the offscreen target's, a
    /// window's swapchain's) and gradient map (of every sample, or coarser:
    /// [`FramePipelines::new`]'s `coarse`).
    pipelines: Vec<((vk::Format, bool), FramePipelines)>,
    pipeline_layout: PipelineLayout,
    /// The capture hook's pipeline, layout, set and set layout.
    capture: Option<(GraphicsPipeline, PipelineLayout, vk::DescriptorSet, DescriptorSetLayout)>,
    pool: DescriptorPool,
    set: vk::DescriptorSet,
    _set_layout: DescriptorSetLayout,
    uniforms: Buffer,
    sampler: Sampler,
    mesh: BlockMesh,
    pub target: Target,
    /// Depth for frames drawn to a window, at its size.
    window_depth: Option<Image>,
    /// Where the terrain pipelines' normals come from.
    normals: NormalSource,
    /// Voids are cut out of the picture (`--voids hole`): shaded forward, where a hole
    /// shows what is behind it.
    holes: bool,
    /// Deferred (the default) or forward shading.
    pixels: PixelPass,
    /// The blocks' depth pass of deferred frames (None without shaderClipDistance:
    /// frames are then shaded forward).
    depth_pipeline: Option<GraphicsPipeline>,
    /// Ray-cast blocks' depth, in deferred frames (`--raycast`).
    raycast_pipeline: Option<GraphicsPipeline>,
    /// The base and detail textures (`--texture`, `--detail`), stretched over the terrain
    /// as in memory, their sampler, and the detail's tiling and weight.
    textures: TextureImages,
    texture_sampler: Sampler,
    detail_tiling: f32,
    detail_weight: f32,
}

/// A swapchain image to draw a frame into: acquired (`acquired` signalled when it may be
/// written), presented once `done` is signalled; left in PRESENT_SRC_KHR.
pub struct WindowImage {
    pub image: vk::Image,
    pub view: vk::ImageView,
    pub format: vk::Format,
    pub extent: vk::Extent2D,
    pub acquired: vk::Semaphore,
    pub done: vk::Semaphore,
}

/// Where a frame goes.
#[derive(Clone, Copy)]
enum Dest<'a> {
    /// The offscreen target, read back.
    ReadBack,
    /// The offscreen target, not read.
    Offscreen,
    Window(&'a WindowImage),
}

/// A streamed frame's pipelines for one colour format. Forward: the blocks shaded, then
/// the in-memory frame's sky where none was drawn (depth still clear: hidden sky is never
/// shaded). Deferred: the blocks' depth (the renderer's `depth_pipeline`), then `shade`
/// over the target.
struct FramePipelines {
    terrain: GraphicsPipeline,
    sky: GraphicsPipeline,
    shade: GraphicsPipeline,
    /// The viewer's F: edges only, shaded forward (where the device draws lines).
    wireframe: Option<GraphicsPipeline>,
}

/// [`FramePipelines`]' handles, for recording.
#[derive(Clone, Copy)]
struct PipelineHandles {
    terrain: vk::Pipeline,
    sky: vk::Pipeline,
    shade: vk::Pipeline,
    /// The terrain pipeline drawing edges only (null without fillModeNonSolid).
    wireframe: vk::Pipeline,
}

impl FramePipelines {
    fn new(
        device: &Arc<Device>,
        layout: &PipelineLayout,
        format: vk::Format,
        normals: NormalSource,
        (base, detail): (bool, bool),
        holes: bool,
        coarse: bool,
    ) -> VkResult<Self> {
        let sky = super::blocks::sky_pipeline(device, layout, format)?;
        let textures = [(layout::SPEC_BASE_TEXTURE, base), (layout::SPEC_DETAIL_TEXTURE, detail)];
        // The deferred pass's shading from the surface as drawn, where the gradient map's
        // samples are coarser than a pixel, exists only when they can be: llvmpipe runs
        // both sides of a branch, and that side was a third of the pass.
        let shade_spec = [textures[0], textures[1], (layout::SPEC_COARSE_GRADIENTS, coarse)];
        // Over the whole target, with the depth attached read-only (as the viewer's
        // panel, drawn in the same rendering, expects), as in memory.
        let shade = GraphicsPipeline::new(
            device,
            &GraphicsPipelineDesc {
                vert: shaders::FULLSCREEN_VERT,
                frag: Some(shaders::STREAM_SHADE_FRAG),
                rasterizer_discard: false,
                vertex_attribute: None,
                color_format: Some(format),
                depth_format: Some(DEPTH_FORMAT),
                depth: DepthMode::Off,
                polygon_mode: vk::PolygonMode::FILL,
                cull_back: false,
                layout,
                specialization: &shade_spec,
            },
        )?;
        let spec = (normals, holes, coarse);
        let terrain = terrain_pipeline(device, layout, format, spec, textures, vk::PolygonMode::FILL)?;
        let wireframe = device
            .features
            .wireframe
            .then(|| terrain_pipeline(device, layout, format, spec, textures, vk::PolygonMode::LINE))
            .transpose()?;
        Ok(FramePipelines { terrain, sky, shade, wireframe })
    }
}

/// The terrain pipeline of streamed frames for colour attachments of `format`, its
/// normals from `normals` (stream.frag: for the gradient map, the held samples' when they
/// are the terrain's, else the surface's derivatives (`coarse`); or the tile's heights),
/// cutting holes if `holes`.
fn terrain_pipeline(
    device: &Arc<Device>,
    layout: &PipelineLayout,
    format: vk::Format,
    (normals, holes, coarse): (NormalSource, bool, bool),
    [base, detail]: [(u32, bool); 2],
    polygon_mode: vk::PolygonMode,
) -> VkResult<GraphicsPipeline> {
    GraphicsPipeline::new(
        device,
        &GraphicsPipelineDesc {
            vert: shaders::STREAM_VERT,
            frag: Some(shaders::STREAM_FRAG),
            rasterizer_discard: false,
            vertex_attribute: Some((2, vk::Format::R8G8_UINT)),
            color_format: Some(format),
            depth_format: Some(DEPTH_FORMAT),
            depth: DepthMode::TestWrite,
            polygon_mode,
            // Seen from above only, as in memory: a camera under the surface sees the sky
            // through it, not its underside (the same mesh, the same winding).
            cull_back: true,
            layout,
            specialization: &[
                (layout::SPEC_NORMALS_FROM_HEIGHTS, normals == NormalSource::Heights),
                (layout::SPEC_HOLES, holes),
                (layout::SPEC_COARSE_GRADIENTS, coarse),
                base,
                detail,
            ],
        },
    )
}

impl StreamedRenderer {
    pub fn new(device: &Arc<Device>, layout: BlockLayout, width: u32, height: u32) -> VkResult<Self> {
        let vertex = vk::ShaderStageFlags::VERTEX;
        let fragment = vk::ShaderStageFlags::FRAGMENT;
        let sampled = vk::DescriptorType::COMBINED_IMAGE_SAMPLER;
        // What the shading reads beside the heights and the frame: `bind` writes them into
        // both sets (the capture set's unread), as lavapipe reads every bound descriptor.
        let shading = [
            (layout::TERRAIN_BINDING_LIGHTING, sampled, fragment),
            (layout::TERRAIN_BINDING_GRADIENTS, sampled, fragment),
            (layout::TERRAIN_BINDING_BASE, sampled, fragment),
            (layout::TERRAIN_BINDING_DETAIL, sampled, fragment),
        ];
        let set_layout = DescriptorSetLayout::new(
            device,
            &[
                // The fragment stage reads the block's tile for its normals.
                (layout::TERRAIN_BINDING_HEIGHTS, sampled, vertex | fragment),
                (layout::TERRAIN_BINDING_FRAME, vk::DescriptorType::UNIFORM_BUFFER, vertex | fragment),
                // The deferred pass's input.
                (layout::TERRAIN_BINDING_DEPTH, sampled, fragment),
            ]
            .into_iter()
            .chain(shading)
            .collect::<Vec<_>>(),
        )?;
        let push = std::mem::size_of::<BlockPush>() as u32;
        let pipeline_layout = PipelineLayout::new(device, &set_layout, push, vertex)?;
        let pipelines = FramePipelines::new(
            device,
            &pipeline_layout,
            COLOR_FORMAT,
            NormalSource::default(),
            (false, false),
            false,
            false,
        )?;
        let depth_pipeline = depth_pass_pipeline(device, &pipeline_layout, shaders::STREAM_DEPTH_VERT)?;
        let raycast_pipeline = (depth_pipeline.as_ref())
            .map(|_| {
                let shaders = (shaders::STREAM_RAYCAST_VERT, shaders::STREAM_RAYCAST_FRAG);
                super::blocks::raycast_pipeline(device, &pipeline_layout, shaders)
            })
            .transpose()?;
        // The capture hook writes from the vertex stage: only where the device allows it.
        let capture = if device.features.vertex_stores {
            let l = DescriptorSetLayout::new(
                device,
                &[
                    (layout::TERRAIN_BINDING_HEIGHTS, sampled, vertex),
                    (layout::TERRAIN_BINDING_FRAME, vk::DescriptorType::UNIFORM_BUFFER, vertex),
                    (layout::CAPTURE_BINDING_POSITIONS, vk::DescriptorType::STORAGE_BUFFER, vertex),
                ]
                .into_iter()
                .chain(shading)
                .collect::<Vec<_>>(),
            )?;
            let pl = PipelineLayout::new(device, &l, push, vertex)?;
            let p = GraphicsPipeline::new(
                device,
                &GraphicsPipelineDesc::vertex_capture(shaders::STREAM_CAPTURE_VERT, &pl),
            )?;
            Some((p, pl, l))
        } else {
            None
        };
        let pool = DescriptorPool::new(
            device,
            2,
            &[
                (vk::DescriptorType::COMBINED_IMAGE_SAMPLER, 11),
                (vk::DescriptorType::UNIFORM_BUFFER, 2),
                (vk::DescriptorType::STORAGE_BUFFER, 1),
            ],
        )?;
        let set = pool.allocate(&set_layout)?;
        let capture = match capture {
            Some((p, pl, l)) => Some((p, pl, pool.allocate(&l)?, l)),
            None => None,
        };
        let uniforms = Buffer::new(
            device,
            "streamed frame uniforms",
            std::mem::size_of::<FrameUniforms>() as u64,
            vk::BufferUsageFlags::UNIFORM_BUFFER,
            gpu_allocator::MemoryLocation::CpuToGpu,
        )?;
        let commands = CommandPool::new(device, device.draw_queue.family)?;
        let cmd = commands.allocate()?;
        let textures = TextureImages::new(device, &commands, None, None)?;
        Ok(StreamedRenderer {
            device: device.clone(),
            layout,
            frame: 0,
            cmd,
            fence: Fence::new(device, true)?,
            timer: FrameTimer::new(device)?,
            commands,
            pipelines: vec![((COLOR_FORMAT, false), pipelines)],
            pipeline_layout,
            capture,
            pool,
            set,
            _set_layout: set_layout,
            uniforms,
            sampler: Sampler::new(device, vk::Filter::NEAREST, vk::SamplerAddressMode::CLAMP_TO_EDGE)?,
            mesh: BlockMesh::new(device, layout.k())?,
            target: Target::new(device, width, height)?,
            window_depth: None,
            normals: NormalSource::default(),
            holes: false,
            pixels: PixelPass::default(),
            depth_pipeline,
            raycast_pipeline,
            textures,
            texture_sampler: Sampler::new(device, vk::Filter::LINEAR, vk::SamplerAddressMode::REPEAT)?,
            detail_tiling: 0.0,
            detail_weight: 1.0,
        })
    }

    /// Draws `base` stretched over the terrain and `detail` repeated `tiling` times across
    /// it, weighted `weight` against it (`--texture`, `--detail`), as in memory; before
    /// the first frame (the pipelines are made again).
    pub fn set_textures(
        &mut self,
        base: Option<&Texture>,
        detail: Option<&Texture>,
        tiling: f32,
        weight: f32,
    ) -> VkResult<()> {
        self.fence.wait(u64::MAX)?;
        self.textures = TextureImages::new(&self.device, &self.commands, base, detail)?;
        (self.detail_tiling, self.detail_weight) = (tiling, weight);
        self.pipelines.clear();
        Ok(())
    }

    /// The frame uniforms of a camera relative to the anchor sample: the in-memory
    /// frame's ramp, sea level and light (its shadows from `view.lighting`).
    fn uniforms(&self, atlas: &HeightAtlas, view: &FrameView) -> VkResult<FrameUniforms> {
        let a =
            |v: i64| i32::try_from(v).map_err(|_| VkError::Setup(format!("anchor sample {v} beyond the i32 range")));
        let (grid, cam) = (view.grid, &view.cam);
        let light = view.light;
        let HeightRange { world, absolute } = view.heights;
        let vp = cam.view_proj();
        Ok(FrameUniforms {
            view_proj: vp.to_cols_array_2d(),
            inv_view_proj: vp.as_dmat4().inverse().as_mat4().to_cols_array_2d(),
            camera_fog: [cam.position.x, cam.position.y, cam.position.z, view.fog],
            terrain: [crate::gpu::layout::ramp_top(absolute), grid.height_scale as f32, world[0], world[1]],
            // z: terrain samples per lighting texel (the lighting lookup); w: samples
            // between the lighting map's heights (the deferred pass's sea share).
            spacing: [
                grid.spacing[0] as f32,
                grid.spacing[1] as f32,
                view.lighting.samples_per_texel() as f32,
                view.lighting.source().stride as f32,
            ],
            light: [light.x, light.y, light.z, 0.25],
            // z: the held samples' gradient map's scale (stream_shade.frag).
            texturing: [
                self.detail_tiling,
                self.detail_weight,
                view.lighting.gradient_scale(),
                crate::lod::heightfield::sea_level(absolute, world),
            ],
            extent: [grid.width as i32, grid.height as i32, 0, self.layout.k() as i32],
            flags: [atlas.unorm16() as i32, i32::from(view.colour_by_lod), 0, 0],
            // As in memory: a plain background is the horizon's colour (the fog's too).
            sky_zenith: [SKY_ZENITH[0], SKY_ZENITH[1], SKY_ZENITH[2], f32::from(u8::from(view.background.is_none()))],
            sky_horizon: match view.background {
                Some([r, g, b]) => [r, g, b, 1.0],
                None => [SKY_HORIZON[0], SKY_HORIZON[1], SKY_HORIZON[2], 1.0],
            },
            anchor: [a(view.anchor[0])?, a(view.anchor[1])?, atlas.side() as i32, 0],
        })
    }

    /// Push constants of each block that has an atlas layer, recording that frame
    /// `self.frame` draws from it; the count of blocks without one; the generation the
    /// frame waits for (`Self::submit_and_wait`).
    #[allow(clippy::type_complexity)]
    fn pushes(
        &self,
        atlas: &HeightAtlas,
        blocks: &[StreamedBlock],
    ) -> (Vec<(BlockPush, u16, Option<[f32; 2]>)>, usize, u64) {
        let mut out = Vec::with_capacity(blocks.len());
        let mut missing = 0;
        let side = atlas.side();
        let (layers, generation) = atlas.draw_layers(blocks.iter().map(|b| b.tile), self.frame);
        assert_eq!(layers.len(), blocks.len(), "a layer (or none) for each block");
        for (sb, layer) in blocks.iter().zip(layers) {
            let Some(layer) = layer else {
                missing += 1;
                continue;
            };
            let b = &sb.block;
            let (ox, oz) = b.origin(&self.layout);
            let c = b.coarser;
            let tile_span = |level: u8| (side as i64 - 3) << level;
            let t = sb.tile;
            let push = BlockPush {
                block: [ox as i32, oz as i32, b.stride() as i32, b.lod as i32],
                coarser_neighbour_stride: [c[0] as i32, c[1] as i32, c[2] as i32, c[3] as i32],
                morph_edges: b.edge_morph.map(morph_value),
                morph: [morph_value(b.morph), 0.0, 0.0, 0.0],
                corner_raw: b.corner_raw.map(|bits| {
                    debug_assert_ne!(bits, CORNER_UNRESOLVED, "streamed blocks are stitched");
                    f32::from_bits(bits)
                }),
                tile: [
                    (i64::from(t.tx) * tile_span(t.level)) as i32,
                    (i64::from(t.tz) * tile_span(t.level)) as i32,
                    i32::from(t.level),
                    layer as i32,
                ],
            };
            out.push((push, b.hidden_parts, sb.raycast));
        }
        (out, missing, generation)
    }

    /// Writes the frame's uniforms and the atlas into the set (after the last frame).
    fn bind(&mut self, atlas: &HeightAtlas, view: &FrameView, set: vk::DescriptorSet) -> VkResult<()> {
        self.fence.wait(u64::MAX)?;
        let u = self.uniforms(atlas, view)?;
        self.uniforms.mapped_mut()?[..std::mem::size_of::<FrameUniforms>()].copy_from_slice(bytemuck::bytes_of(&u));
        self.pool.write(
            set,
            &[
                (layout::TERRAIN_BINDING_HEIGHTS, atlas.image().view, self.sampler.handle),
                (layout::TERRAIN_BINDING_LIGHTING, view.lighting.map.image.view, view.lighting.map.sampler.handle),
                (layout::TERRAIN_BINDING_GRADIENTS, view.lighting.gradients_view(), self.sampler.handle),
                (layout::TERRAIN_BINDING_BASE, self.textures.base.view, self.texture_sampler.handle),
                (layout::TERRAIN_BINDING_DETAIL, self.textures.detail.view, self.texture_sampler.handle),
            ],
            &[(layout::TERRAIN_BINDING_FRAME, self.uniforms.handle, std::mem::size_of::<FrameUniforms>() as u64)],
        );
        Ok(())
    }

    /// Submits the recorded command buffer and waits for it; `window`: the acquire
    /// semaphore waited before colour output, the present semaphore signalled. The frame
    /// waits for the atlas generation `generation` at the vertex shader (finished already:
    /// the wait costs nothing and makes the upload's writes visible across queues) and
    /// signals its number on the atlas's frame timeline (layers it drew may be rewritten
    /// once that value is reached).
    fn submit_and_wait(
        &mut self,
        atlas: &HeightAtlas,
        generation: u64,
        window: Option<(vk::Semaphore, vk::Semaphore)>,
    ) -> VkResult<()> {
        // SAFETY: `cmd` is recording on this thread.
        unsafe { self.device.raw.end_command_buffer(self.cmd) }.vk("vkEndCommandBuffer")?;
        self.fence.reset()?;
        let cmds = [vk::CommandBufferSubmitInfo::default().command_buffer(self.cmd)];
        let mut waits: Vec<_> = window
            .iter()
            .map(|w| {
                vk::SemaphoreSubmitInfo::default()
                    .semaphore(w.0)
                    .stage_mask(vk::PipelineStageFlags2::COLOR_ATTACHMENT_OUTPUT)
            })
            .collect();
        if generation > 0 {
            waits.push(
                vk::SemaphoreSubmitInfo::default()
                    .semaphore(atlas.generations())
                    .value(generation)
                    .stage_mask(vk::PipelineStageFlags2::VERTEX_SHADER),
            );
        }
        let mut signals: Vec<_> = window
            .iter()
            .map(|w| {
                vk::SemaphoreSubmitInfo::default().semaphore(w.1).stage_mask(vk::PipelineStageFlags2::ALL_COMMANDS)
            })
            .collect();
        signals.push(
            vk::SemaphoreSubmitInfo::default()
                .semaphore(atlas.frames())
                .value(self.frame)
                .stage_mask(vk::PipelineStageFlags2::ALL_COMMANDS),
        );
        let submit = vk::SubmitInfo2::default()
            .command_buffer_infos(&cmds)
            .wait_semaphore_infos(&waits)
            .signal_semaphore_infos(&signals);
        self.device.draw_queue.submit(&self.device, &[submit], self.fence.handle)?;
        self.fence.wait(u64::MAX)
    }

    /// The pipelines for colour attachments of `format` and a gradient map coarser than
    /// the terrain's samples (`coarse`), made the first time.
    fn pipeline(&mut self, format: vk::Format, coarse: bool) -> VkResult<PipelineHandles> {
        let handles = |p: &FramePipelines| PipelineHandles {
            terrain: p.terrain.handle,
            sky: p.sky.handle,
            shade: p.shade.handle,
            wireframe: p.wireframe.as_ref().map_or(vk::Pipeline::null(), |w| w.handle),
        };
        if let Some((_, p)) = self.pipelines.iter().find(|(key, _)| *key == (format, coarse)) {
            return Ok(handles(p));
        }
        let textures = (self.textures.has_base, self.textures.has_detail);
        let (device, layout) = (&self.device, &self.pipeline_layout);
        let p = FramePipelines::new(device, layout, format, self.normals, textures, self.holes, coarse)?;
        let h = handles(&p);
        self.pipelines.push(((format, coarse), p));
        Ok(h)
    }

    /// Normals from `normals` from now on (`--shading`; [`NormalSource::GradientMap`], the
    /// default, takes them from the held samples' gradient map, and where those are
    /// coarser than the terrain's up close from the surface as drawn). Before the first
    /// frame: the pipelines of the other source are destroyed.
    pub fn set_normals(&mut self, normals: NormalSource) {
        if normals != self.normals {
            self.normals = normals;
            self.pipelines.clear();
        }
    }

    /// Cuts voids out of the picture from now on (`--voids hole`; the atlas says which
    /// samples are voids); before the first frame, as [`StreamedRenderer::set_normals`].
    pub fn set_holes(&mut self, holes: bool) {
        if holes != self.holes {
            self.holes = holes;
            self.pipelines.clear();
        }
    }

    /// Triangles of a block's outer ring, which a ray-cast block still rasterizes.
    pub fn ring_triangles(&self) -> u64 {
        u64::from(self.mesh.ring_count / 3)
    }

    /// Deferred (the default) or forward shading from now on (`--pixels`).
    pub fn set_pixels(&mut self, pixels: PixelPass) {
        self.pixels = pixels;
    }

    /// The shading asked for ([`StreamedRenderer::set_pixels`]).
    pub fn pixels(&self) -> PixelPass {
        self.pixels
    }

    /// Whether the frame seen by `view` is shaded deferred: asked for, with flat normals
    /// (the tile's heights are out of the deferred pass's reach), not coloured by LOD (the
    /// block that drew a pixel is not kept), with the lighting map's heights (the sea
    /// share), and near enough to the terrain for depth to give the points forward
    /// shading shades (as in memory).
    fn deferred(&self, view: &FrameView) -> bool {
        let g = view.grid;
        let (a, s) = (view.anchor, g.spacing);
        // The terrain's box relative to the anchor (f64: the anchor may be far out).
        let rel = |i: i64, n: usize, s: f64| [(-i as f64 * s) as f32, ((n as i64 - 1 - i) as f64 * s) as f32];
        let (x, z) = (rel(a[0], g.width, s[0]), rel(a[1], g.height, s[1]));
        let [lo, hi] = view.heights.world;
        let distance = crate::lod::camera::distance_to_aabb(
            view.cam.position,
            glam::Vec3::new(x[0], lo, z[0]),
            glam::Vec3::new(x[1], hi, z[1]),
        );
        self.pixels == PixelPass::Deferred
            && self.normals == NormalSource::GradientMap
            && !self.holes
            && self.depth_pipeline.is_some()
            && !view.colour_by_lod
            && !view.wireframe
            && view.lighting.holds_heights()
            && depth_precise_at(distance, s[0].min(s[1]) as f32)
    }

    /// Offscreen frames at `width x height` from now on.
    pub fn resize(&mut self, width: u32, height: u32) -> VkResult<()> {
        if (self.target.width, self.target.height) != (width, height) {
            self.fence.wait(u64::MAX)?; // the old target's last frame
            self.target = Target::new(&self.device, width, height)?;
        }
        Ok(())
    }

    /// Draws `blocks` from `atlas` as seen by `view`, waits, and returns the RGBA8 (sRGB)
    /// pixels.
    pub fn render(
        &mut self,
        atlas: &HeightAtlas,
        view: &FrameView,
        blocks: &[StreamedBlock],
    ) -> VkResult<(Vec<u8>, StreamedStats)> {
        let stats = self.draw(atlas, view, blocks, Dest::ReadBack, None)?;
        Ok((self.target.pixels()?, stats))
    }

    /// Draws `blocks` offscreen and waits, reading nothing back (a benchmark's frames).
    pub fn render_unread(
        &mut self,
        atlas: &HeightAtlas,
        view: &FrameView,
        blocks: &[StreamedBlock],
    ) -> VkResult<StreamedStats> {
        self.draw(atlas, view, blocks, Dest::Offscreen, None)
    }

    /// Draws `blocks` into a window's swapchain image (the view's size must be the
    /// image's) and waits; the caller presents it. `overlay` records more drawing (the
    /// panel) into the frame's rendering after the terrain.
    pub fn render_to_window(
        &mut self,
        atlas: &HeightAtlas,
        view: &FrameView,
        blocks: &[StreamedBlock],
        window: &WindowImage,
        overlay: Option<Overlay>,
    ) -> VkResult<StreamedStats> {
        let e = window.extent;
        if self.window_depth.as_ref().is_none_or(|d| d.extent != e) {
            self.window_depth = None; // the last frame was waited for
            self.window_depth = Some(super::blocks::depth_target(&self.device, "window depth", e)?);
        }
        self.draw(atlas, view, blocks, Dest::Window(window), overlay)
    }

    fn draw(
        &mut self,
        atlas: &HeightAtlas,
        view: &FrameView,
        blocks: &[StreamedBlock],
        dest: Dest,
        overlay: Option<Overlay>,
    ) -> VkResult<StreamedStats> {
        let window = match dest {
            Dest::Window(w) => Some(w),
            _ => None,
        };
        let set = self.set;
        self.bind(atlas, view, set)?;
        self.frame += 1;
        let (pushes, missing, generation) = self.pushes(atlas, blocks);
        let mut stats = StreamedStats { blocks: pushes.len(), missing, ..StreamedStats::default() };
        let format = window.map_or(COLOR_FORMAT, |w| w.format);
        let pipelines = self.pipeline(format, view.lighting.source().stride > 1)?;
        let deferred = self.deferred(view);
        let d = self.device.raw.clone();
        let cmd = self.cmd;
        let (color, color_view, depth, extent) = match window {
            Some(w) => (w.image, w.view, self.window_depth.as_ref().expect("made for the window"), w.extent),
            None => {
                let t = &self.target;
                (t.color.handle, t.color.view, &t.depth, vk::Extent2D { width: t.width, height: t.height })
            }
        };
        // Rewritten every frame, forward ones included (lavapipe reads every descriptor of
        // a bound set, used or not): the depth image is the destination's.
        self.pool.write_in_layout(
            set,
            &[(layout::TERRAIN_BINDING_DEPTH, depth.view, self.sampler.handle)],
            vk::ImageLayout::DEPTH_READ_ONLY_OPTIMAL,
            &[],
        );
        let area = vk::Rect2D { offset: vk::Offset2D::default(), extent };
        let clear = [SKY_HORIZON[0], SKY_HORIZON[1], SKY_HORIZON[2], 1.0];
        let color_att = [vk::RenderingAttachmentInfo::default()
            .image_view(color_view)
            .image_layout(vk::ImageLayout::COLOR_ATTACHMENT_OPTIMAL)
            // The deferred shading pass writes every pixel.
            .load_op(if deferred { vk::AttachmentLoadOp::DONT_CARE } else { vk::AttachmentLoadOp::CLEAR })
            .store_op(vk::AttachmentStoreOp::STORE)
            .clear_value(vk::ClearValue { color: vk::ClearColorValue { float32: clear } })];
        let depth_att = vk::RenderingAttachmentInfo::default()
            .image_view(depth.view)
            .image_layout(vk::ImageLayout::DEPTH_ATTACHMENT_OPTIMAL)
            .load_op(vk::AttachmentLoadOp::CLEAR)
            .store_op(if deferred { vk::AttachmentStoreOp::STORE } else { vk::AttachmentStoreOp::DONT_CARE })
            .clear_value(vk::ClearValue { depth_stencil: vk::ClearDepthStencilValue { depth: 0.0, stencil: 0 } });
        let rendering = vk::RenderingInfo::default().render_area(area).layer_count(1).depth_attachment(&depth_att);
        // Deferred: the blocks write depth only.
        let rendering = if deferred { rendering } else { rendering.color_attachments(&color_att) };
        let viewport = vk::Viewport {
            x: 0.0,
            y: 0.0,
            width: extent.width as f32,
            height: extent.height as f32,
            min_depth: 0.0,
            max_depth: 1.0,
        };
        let rendered = (
            vk::PipelineStageFlags2::COLOR_ATTACHMENT_OUTPUT,
            vk::AccessFlags2::COLOR_ATTACHMENT_WRITE,
            vk::ImageLayout::COLOR_ATTACHMENT_OPTIMAL,
        );
        // The image's last use: the previous frame's drawing and readback copy, or the
        // presentation engine's read (ordered by the acquire semaphore, waited at colour
        // output).
        let last_use = match window {
            Some(_) => (vk::PipelineStageFlags2::COLOR_ATTACHMENT_OUTPUT, vk::AccessFlags2::NONE),
            None => (
                vk::PipelineStageFlags2::COPY | vk::PipelineStageFlags2::COLOR_ATTACHMENT_OUTPUT,
                vk::AccessFlags2::TRANSFER_READ | vk::AccessFlags2::COLOR_ATTACHMENT_WRITE,
            ),
        };
        let blocks_pipeline = match (deferred, &self.depth_pipeline) {
            (true, Some(p)) => p.handle,
            _ if view.wireframe && pipelines.wireframe != vk::Pipeline::null() => pipelines.wireframe,
            _ => pipelines.terrain,
        };
        // SAFETY: the fence was waited in `bind`, so `cmd` is free; every object bound
        // lives in `self`, `atlas` or the caller's swapchain and outlives the wait in
        // `submit_and_wait`.
        unsafe {
            begin_one_time(&d, cmd)?;
            if let Some(t) = &self.timer {
                t.begin(&d, cmd);
            }
            attachment_barriers(&d, cmd, color, last_use, depth);
            d.cmd_begin_rendering(cmd, &rendering);
            d.cmd_set_viewport(cmd, 0, &[viewport]);
            d.cmd_set_scissor(cmd, 0, &[area]);
            d.cmd_bind_pipeline(cmd, vk::PipelineBindPoint::GRAPHICS, blocks_pipeline);
            d.cmd_bind_descriptor_sets(
                cmd,
                vk::PipelineBindPoint::GRAPHICS,
                self.pipeline_layout.handle,
                0,
                &[set],
                &[],
            );
            d.cmd_bind_vertex_buffers(cmd, 0, &[self.mesh.vertices.handle], &[0]);
            d.cmd_bind_index_buffer(cmd, self.mesh.indices.handle, 0, self.mesh.index_type);
            let push = |p: &BlockPush| {
                let bytes = bytemuck::bytes_of(p);
                d.cmd_push_constants(cmd, self.pipeline_layout.handle, vk::ShaderStageFlags::VERTEX, 0, bytes);
            };
            // Rays write depth only: in deferred frames (as in memory).
            let raycast = self.raycast_pipeline.as_ref().filter(|_| deferred);
            let cast = |c: &Option<[f32; 2]>| raycast.is_some() && c.is_some();
            for (p, hidden, _) in pushes.iter().filter(|(_, _, c)| !cast(c)) {
                push(p);
                // Parts outside the frustum left out, as in memory.
                let [hidden, triangles, draws] = draw_visible_parts(&d, cmd, &self.mesh, &self.layout, *hidden);
                stats.hidden_parts += hidden;
                stats.triangles += triangles;
                stats.draw_calls += draws;
            }
            if let Some(raycast) = raycast {
                // As in memory: each ray-cast block's outer ring as triangles, then the
                // rays, after every rasterized triangle.
                let cast_blocks = || pushes.iter().filter(|(_, _, c)| cast(c));
                for (p, _, _) in cast_blocks() {
                    push(p);
                    d.cmd_draw_indexed(cmd, self.mesh.ring_count, 1, self.mesh.ring_first, 0, 0);
                    stats.triangles += u64::from(self.mesh.ring_count / 3);
                    stats.draw_calls += 1;
                }
                d.cmd_bind_pipeline(cmd, vk::PipelineBindPoint::GRAPHICS, raycast.handle);
                for (p, _, range) in cast_blocks() {
                    // The block's range rides in the morph's unused lanes: a ray-cast
                    // block does not morph (raycast_vert.glsl).
                    let [lo, hi] = range.expect("a ray-cast block has its range");
                    push(&BlockPush { morph: [p.morph[0], lo, hi, 0.0], ..*p });
                    // The box: 6 faces of 2 triangles, made by the vertex stage.
                    d.cmd_draw(cmd, 36, 1, 0, 0);
                    stats.raycast_blocks += 1;
                    stats.draw_calls += 1;
                }
            }
            if deferred {
                begin_shading_pass(&d, cmd, depth, area, &color_att);
                d.cmd_bind_pipeline(cmd, vk::PipelineBindPoint::GRAPHICS, pipelines.shade);
            } else {
                d.cmd_bind_pipeline(cmd, vk::PipelineBindPoint::GRAPHICS, pipelines.sky);
            }
            // The shading pass or the sky: one triangle over the target.
            d.cmd_draw(cmd, 3, 1, 0, 0);
            if let Some(draw) = overlay {
                draw(cmd);
            }
            d.cmd_end_rendering(cmd);
            match dest {
                Dest::Window(_) => {
                    let present =
                        (vk::PipelineStageFlags2::NONE, vk::AccessFlags2::NONE, vk::ImageLayout::PRESENT_SRC_KHR);
                    image_barrier(&d, cmd, color, COLOR_RANGE, rendered, present);
                }
                Dest::ReadBack => {
                    image_barrier(&d, cmd, color, COLOR_RANGE, rendered, crate::vk::COPY_SOURCE);
                    crate::vk::copy_image_to_host(&d, cmd, color, extent, self.target.readback.handle);
                    self.target.set_read_back(true);
                }
                Dest::Offscreen => self.target.set_read_back(false),
            }
            if let Some(t) = &self.timer {
                t.end(&d, cmd);
            }
        }
        stats.deferred = deferred;
        self.submit_and_wait(atlas, generation, window.map(|w| (w.acquired, w.done)))?;
        // The frame was waited for: its timestamps are in the buffer.
        stats.gpu_ms = self.timer.as_ref().map(|t| t.read().map(|r| r.1)).transpose()?;
        Ok(stats)
    }

    /// Test hook: the position (relative to the anchor) the vertex shader gives every
    /// vertex of `blocks` (`k * k` a block, row-major), from glsl/stream_capture.vert.
    pub fn capture(
        &mut self,
        atlas: &HeightAtlas,
        view: &FrameView,
        blocks: &[StreamedBlock],
    ) -> VkResult<Vec<[f32; 4]>> {
        let Some((pipeline, pipeline_layout, set, _)) = &self.capture else {
            return Err(VkError::Setup("vertex capture needs vertexPipelineStoresAndAtomics".into()));
        };
        let set = *set;
        let k = self.layout.k() as usize;
        let positions = Buffer::new(
            &self.device,
            "captured streamed vertices",
            (blocks.len().max(1) * k * k * 16) as u64,
            vk::BufferUsageFlags::STORAGE_BUFFER,
            gpu_allocator::MemoryLocation::GpuToCpu,
        )?;
        let (pipeline, pipeline_layout) = (pipeline.handle, pipeline_layout.handle);
        self.bind(atlas, view, set)?;
        let storage = [vk::DescriptorBufferInfo { buffer: positions.handle, offset: 0, range: vk::WHOLE_SIZE }];
        let write = vk::WriteDescriptorSet::default()
            .dst_set(set)
            .dst_binding(layout::CAPTURE_BINDING_POSITIONS)
            .descriptor_type(vk::DescriptorType::STORAGE_BUFFER)
            .buffer_info(&storage);
        self.frame += 1;
        let (pushes, missing, generation) = self.pushes(atlas, blocks);
        if missing > 0 {
            return Err(VkError::Setup(format!("{missing} blocks have no atlas layer")));
        }
        let d = self.device.raw.clone();
        let cmd = self.cmd;
        // SAFETY: the set is new; the fence was waited in `bind`; every object outlives
        // the wait in `submit_and_wait`.
        unsafe {
            d.update_descriptor_sets(&[write], &[]);
            super::blocks::record_capture(
                &d,
                cmd,
                (pipeline, pipeline_layout, set),
                &self.mesh,
                &pushes.iter().map(|(p, _, _)| *p).collect::<Vec<_>>(),
                positions.handle,
            )?;
        }
        self.submit_and_wait(atlas, generation, None)?;
        let floats: Vec<f32> = bytemuck::pod_collect_to_vec(&positions.mapped()?[..blocks.len() * k * k * 16]);
        Ok(floats.chunks(4).map(|c| [c[0], c[1], c[2], c[3]]).collect())
    }
}

/// Records more drawing (a panel) into a frame's rendering, after the terrain.
pub type Overlay<'a> = &'a mut dyn FnMut(vk::CommandBuffer);

/// What the colours of a streamed terrain need of its heights, as in memory: the world
/// heights its samples span (the ramp, the sea level) and whether they are metres above
/// sea level (the ramp over absolute heights, sea at 0 m).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct HeightRange {
    pub world: [f32; 2],
    pub absolute: bool,
}

/// What a streamed frame is seen from: the grid, the anchor sample and the camera
/// relative to it ([`crate::stream::traverse::View::relative`]), and the terrain's
/// heights for its colours.
pub struct FrameView<'a> {
    pub grid: &'a Grid,
    pub anchor: [i64; 2],
    pub cam: Camera,
    pub heights: HeightRange,
    /// Exponential fog density per world unit.
    pub fog: f32,
    /// Unit vector towards the sun (`--sun`: its direction).
    pub light: glam::Vec3,
    /// Sun visibility and ambient occlusion.
    pub lighting: &'a OwnLighting,
    /// Blocks tinted by their LOD (`--colour-by-lod`, the viewer's L), as in memory.
    pub colour_by_lod: bool,
    /// Edges only (the viewer's F), where the device draws lines, as in memory.
    pub wireframe: bool,
    /// A plain background instead of the sky (`--background`, linear RGB).
    pub background: Option<[f32; 3]>,
}

impl Drop for StreamedRenderer {
    fn drop(&mut self) {
        // The last frame before the pool, pipelines and buffers go.
        let _ = self.fence.wait(u64::MAX);
        self.commands.free(self.cmd);
    }
}

/// The heights streamed frames' lighting map is made from, and their stride: the tiles of
/// the level whose vertices fall one to a texel of the map the same terrain gets in
/// memory (at most the top level; 64 tiles or fewer whatever the terrain's size), read
/// from `source` (`name`: the archive, for errors that do not name it already); `None`
/// for a strip too long and narrow for any (3 samples across in at most
/// `MAX_LIGHTING_SIDE` a side). Stops between tiles once `stop` is set (a stop request):
/// an error then.
pub fn lighting_heights(
    source: &dyn TileSource,
    grid: &Grid,
    name: &str,
    stop: Option<&std::sync::atomic::AtomicBool>,
) -> anyhow::Result<Option<(Heightfield, usize)>> {
    let (n, roots) = crate::lod::heightfield::grid_cover(grid.width, grid.height);
    let side = roots.iter().map(|r| r * (1 << n) + 1).max().unwrap_or(1);
    // At most `MAX_LIGHTING_SIDE` texels a side, and at least 3 samples along the
    // narrower side (a heightfield's least): a strip too long and narrow for both has no
    // map.
    let level = (samples_per_texel(side, MAX_LIGHTING_SIDE).trailing_zeros() as u8).min(grid.top);
    let narrow = grid.width.min(grid.height).saturating_sub(1).max(2);
    if (narrow >> level) < 2 {
        return Ok(None);
    }
    let terrain = LevelTerrain {
        name,
        extent: [grid.width, grid.height],
        tile_quads: grid.tile_quads,
        format: if grid.height_bytes == 2 { HeightFormat::Unorm16 } else { HeightFormat::Float32 },
        spacing: grid.spacing.map(|s| s as f32),
        height_scale: grid.height_scale as f32,
    };
    let stopped = || stop.is_some_and(|s| s.load(std::sync::atomic::Ordering::SeqCst));
    let hf = level_heightfield(&terrain, level, |tx, tz| {
        if stopped() {
            return Err(anyhow::anyhow!("stopped"));
        }
        match source.read(TileKey { level, tx, tz }) {
            Ok(Some((tile, _))) => Ok(tile),
            Ok(None) => Err(HeightfieldError::invalid(name, format!("tile {level}/{tx}/{tz} is missing")).into()),
            Err(e) => Err(anyhow::anyhow!(e)),
        }
    })?;
    Ok(Some((hf, 1 << level)))
}
