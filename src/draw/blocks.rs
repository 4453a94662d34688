//! The blocks rendering activity's GPU side (SPEC section 5): one k x k vertex/index
//! buffer, placed per block by push constants, heights fetched in the vertex shader.
//! This module records and submits frames; the draw thread (see `render`) decides what
//! to draw.

use crate::draw::lighting::{LightingSource, Sun};
use crate::draw::lighting_gpu::LightingMap;
use crate::draw::raycast::{self, Raycast};
use crate::gpu::layout::{self as layout, BlockPush, FrameUniforms};
use crate::gpu::shaders;
use crate::gpu::terrain::TerrainGpu;
use crate::lod::block::{morph_value, BlockLayout, DrawBlock};
use crate::lod::camera::Camera;
use crate::lod::heightfield::Heightfield;
use crate::vk::{
    begin_one_time, host_read_barrier, image_barrier, vk, Buffer, CommandPool, DepthMode, DescriptorPool,
    DescriptorSetLayout, Device, Fence, FrameTimer, GraphicsPipeline, GraphicsPipelineDesc, Image, PipelineLayout,
    VkResult, VkResultExt,
};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;

pub const COLOR_FORMAT: vk::Format = vk::Format::R8G8B8A8_SRGB;
pub const DEPTH_FORMAT: vk::Format = vk::Format::D32_SFLOAT;

/// The shared block mesh: vertex `(u, v)` as two bytes, quads split along the a-i
/// diagonal (SPEC section 2).
pub struct BlockMesh {
    pub vertices: Buffer,
    pub indices: Buffer,
    pub index_count: u32,
    /// The outer ring of quads, after the whole mesh in `indices`: what a ray-cast block
    /// rasterizes too, so that where it meets another block the rasterizer decides.
    pub ring_first: u32,
    pub ring_count: u32,
    pub index_type: vk::IndexType,
    pub bytes: u64,
}

impl BlockMesh {
    pub fn new(device: &Arc<Device>, k: u32) -> VkResult<Self> {
        let (verts, mut idx) = crate::lod::block::block_mesh_data(k);
        let ring = crate::lod::block::ring_indices(&idx, k);
        let (whole, ring_count) = (idx.len() as u32, ring.len() as u32);
        idx.extend(ring);
        let (index_bytes, index_type) = if k * k <= 65536 {
            let v: Vec<u16> = idx.iter().map(|&i| i as u16).collect();
            (bytemuck::cast_slice(&v).to_vec(), vk::IndexType::UINT16)
        } else {
            (bytemuck::cast_slice(&idx).to_vec(), vk::IndexType::UINT32)
        };
        let vertices = Buffer::with_data(device, "block vertices", &verts, vk::BufferUsageFlags::VERTEX_BUFFER)?;
        let indices = Buffer::with_data(device, "block indices", &index_bytes, vk::BufferUsageFlags::INDEX_BUFFER)?;
        Ok(BlockMesh {
            bytes: (verts.len() + index_bytes.len()) as u64,
            vertices,
            indices,
            index_count: whole,
            ring_first: whole,
            ring_count,
            index_type,
        })
    }
}

/// Shading settings that are not part of the camera.
#[derive(Clone, Copy, Debug)]
pub struct Shading {
    pub fog_density: f32,
    pub sky: bool,
    /// Background colour when `sky` is off (the crack test looks for it).
    pub background: [f32; 3],
    pub colour_by_lod: bool,
    pub wireframe: bool,
    pub detail_tiling: f32,
    pub detail_weight: f32,
    pub normals: NormalSource,
    pub pixels: PixelPass,
    /// Blocks drawn by the ray-caster instead of as triangles (deferred frames only).
    pub raycast: Raycast,
}

/// How terrain pixels are shaded (the same image up to rounding:
/// `tests/gpu_render.rs::deferred_shading_matches_forward`).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, clap::ValueEnum)]
pub enum PixelPass {
    /// The blocks write depth only, then one pass over the target shades each visible
    /// pixel once, from its depth.
    #[default]
    Deferred,
    /// Each block's fragments are shaded as it is drawn, partly covered 2x2 quads
    /// included (colour-by-LOD and wireframe always use it).
    Forward,
}

impl Shading {
    /// Whether this frame asks for deferred shading: the colour-by-LOD and wireframe
    /// views need the block that drew a pixel, which depth alone does not give.
    fn deferred(&self) -> bool {
        self.pixels == PixelPass::Deferred && !self.colour_by_lod && !self.wireframe
    }
}

/// Where the terrain shader's normals come from (the image is the same up to rounding).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, clap::ValueEnum)]
pub enum NormalSource {
    /// A per-sample gradient map computed at load: four fetches per pixel.
    #[default]
    GradientMap,
    /// Sixteen height fetches per pixel: no map to make at load, more work a pixel.
    Heights,
}

/// What selects a terrain pipeline: the shading switches compiled in as specialization
/// constants (the textures are fixed per renderer), and the polygon mode.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
struct TerrainVariant {
    normals: NormalSource,
    colour_by_lod: bool,
    wireframe: bool,
    /// The deferred shading pass (shade.frag) rather than the forward block pipeline.
    deferred: bool,
}

/// The pipelines a frame is drawn with.
#[derive(Clone, Copy)]
struct FramePipelines {
    /// Draws the blocks: shaded (forward) or depth only (deferred).
    blocks: vk::Pipeline,
    /// Ray-cast blocks' depth (deferred frames that ray-cast any).
    raycast: Option<vk::Pipeline>,
    /// Deferred shading's pass over the target, after the blocks.
    shade: Option<vk::Pipeline>,
}

impl Default for Shading {
    fn default() -> Self {
        Shading {
            fog_density: 0.0,
            sky: true,
            background: [1.0, 0.0, 1.0],
            colour_by_lod: false,
            wireframe: false,
            detail_tiling: 64.0,
            detail_weight: 1.0,
            normals: NormalSource::GradientMap,
            pixels: PixelPass::Deferred,
            raycast: Raycast::Off,
        }
    }
}

/// Sky colour straight up.
pub const SKY_ZENITH: [f32; 3] = [0.16, 0.33, 0.66];
/// Sky and fog colour at the horizon (also the clear colour).
pub const SKY_HORIZON: [f32; 3] = [0.62, 0.72, 0.84];

/// Offscreen colour + depth targets and their readback buffer.
pub struct Target {
    pub color: Image,
    pub depth: Image,
    pub readback: Buffer,
    pub width: u32,
    pub height: u32,
    /// Whether the last frame submitted into this target copies its image into
    /// `readback` ([`BlocksRenderer::submit_offscreen`]).
    read_back: AtomicBool,
}

impl Target {
    /// The last finished frame's RGBA8 pixels (the readback buffer).
    ///
    /// # Panics
    /// If that frame was submitted without its readback: the buffer would hold an older
    /// frame.
    pub fn pixels(&self) -> VkResult<Vec<u8>> {
        assert!(self.read_back.load(Ordering::Relaxed), "the target's last frame was not read back");
        Ok(self.readback.mapped()?[..(self.width * self.height * 4) as usize].to_vec())
    }

    /// Records whether the frame being recorded into the target copies into `readback`.
    pub(crate) fn set_read_back(&self, yes: bool) {
        self.read_back.store(yes, Ordering::Relaxed);
    }

    pub fn new(device: &Arc<Device>, width: u32, height: u32) -> VkResult<Self> {
        let extent = vk::Extent2D { width, height };
        Ok(Target {
            color: Image::new(
                device,
                "colour target",
                extent,
                COLOR_FORMAT,
                1,
                vk::ImageUsageFlags::COLOR_ATTACHMENT | vk::ImageUsageFlags::TRANSFER_SRC,
                false,
            )?,
            depth: depth_target(device, "depth target", extent)?,
            readback: Buffer::new(
                device,
                "frame readback",
                width as u64 * height as u64 * 4,
                vk::BufferUsageFlags::TRANSFER_DST,
                gpu_allocator::MemoryLocation::GpuToCpu,
            )?,
            width,
            height,
            read_back: AtomicBool::new(false),
        })
    }
}

/// Sample spacings from the terrain's box beyond which frames are shaded forward.
/// Deferred shading recovers a pixel's position from 32-bit depth, good to about 6e-8 of
/// the distance: a telephoto view from 10^6 spacings away shades points a visible
/// fraction of a sample off (an adversarial review's plateau at 1280 x 720: RMSE 1.66
/// against forward from 1.4 x 10^6 spacings, 0.16 from 4 x 10^5, 0.12 from 1.4 x 10^5;
/// `tests/gpu_render.rs::far_telephoto_views_match_forward`).
pub const DEFERRED_MAX_SPACINGS: f32 = 1e5;

/// Whether `cam` is near enough to the terrain for deferred shading to shade the points
/// forward shading does.
pub fn depth_precise_enough(hf: &Heightfield, terrain: &TerrainGpu, cam: &Camera) -> bool {
    let (wx, wz) = hf.world_extent();
    let min = glam::Vec3::new(0.0, terrain.raw_range[0] * hf.height_scale, 0.0);
    let max = glam::Vec3::new(wx, terrain.raw_range[1] * hf.height_scale, wz);
    depth_precise_at(crate::lod::camera::distance_to_aabb(cam.position, min, max), hf.spacing.min())
}

/// Whether a camera `distance` world units from the terrain's box, over samples at least
/// `spacing` apart, is near enough for deferred shading (both renderers).
pub fn depth_precise_at(distance: f32, spacing: f32) -> bool {
    distance <= DEFERRED_MAX_SPACINGS * spacing
}

/// The sky behind the terrain (`sky.frag`), drawn after the blocks where none was (depth
/// still clear: hidden sky is never shaded), for colour attachments of `format`; reads
/// only the frame uniforms of `layout`'s set.
pub fn sky_pipeline(device: &Arc<Device>, layout: &PipelineLayout, format: vk::Format) -> VkResult<GraphicsPipeline> {
    GraphicsPipeline::new(
        device,
        &GraphicsPipelineDesc {
            vert: shaders::FULLSCREEN_VERT,
            frag: Some(shaders::SKY_FRAG),
            rasterizer_discard: false,
            vertex_attribute: None,
            color_format: Some(format),
            depth_format: Some(DEPTH_FORMAT),
            depth: DepthMode::Background,
            polygon_mode: vk::PolygonMode::FILL,
            cull_back: false,
            layout,
            specialization: &[],
        },
    )
}

/// The depth pass of deferred frames: the blocks placed by vertex shader `vert` (which
/// clips the margin beyond the true extent), no fragment shader; None where the device
/// cannot clip (`shaderClipDistance`: frames are then shaded forward).
pub fn depth_pass_pipeline(
    device: &Arc<Device>,
    layout: &PipelineLayout,
    vert: &'static [u8],
) -> VkResult<Option<GraphicsPipeline>> {
    if !device.features.clip_distance {
        return Ok(None);
    }
    let desc = GraphicsPipelineDesc {
        vert,
        frag: None,
        rasterizer_discard: false,
        vertex_attribute: Some((2, vk::Format::R8G8_UINT)),
        color_format: None,
        depth_format: Some(DEPTH_FORMAT),
        depth: DepthMode::TestWrite,
        polygon_mode: vk::PolygonMode::FILL,
        // A heightfield is seen from above only (as the forward pipelines).
        cull_back: true,
        layout,
        specialization: &[],
    };
    Ok(Some(GraphicsPipeline::new(device, &desc)?))
}

/// The ray-cast blocks' pipeline (`raycast_vert.glsl`, `raycast_frag.glsl`): depth only,
/// for deferred frames, from the shaders `(vert, frag)` of the frame's heights.
pub fn raycast_pipeline(
    device: &Arc<Device>,
    layout: &PipelineLayout,
    (vert, frag): (&'static [u8], &'static [u8]),
) -> VkResult<GraphicsPipeline> {
    GraphicsPipeline::new(
        device,
        &GraphicsPipelineDesc {
            vert,
            frag: Some(frag),
            rasterizer_discard: false,
            vertex_attribute: None,
            color_format: None,
            depth_format: Some(DEPTH_FORMAT),
            depth: DepthMode::TestWrite,
            polygon_mode: vk::PolygonMode::FILL,
            // The vertex stage keeps the box's far faces only.
            cull_back: false,
            layout,
            specialization: &[],
        },
    )
}

/// A depth attachment that the deferred shading pass also samples.
pub fn depth_target(device: &Arc<Device>, name: &str, extent: vk::Extent2D) -> VkResult<Image> {
    let usage = vk::ImageUsageFlags::DEPTH_STENCIL_ATTACHMENT | vk::ImageUsageFlags::SAMPLED;
    Image::new(device, name, extent, DEPTH_FORMAT, 1, usage, false)
}

/// Where [`BlocksRenderer::record_frame`] draws, and what happens to the image after.
pub struct FrameDest<'a> {
    pub image: vk::Image,
    pub view: vk::ImageView,
    pub extent: vk::Extent2D,
    pub depth: &'a Image,
    /// Stage and access that last touched `image` (its old contents are discarded).
    pub last_use: (vk::PipelineStageFlags2, vk::AccessFlags2),
    /// Copy the frame into this host-visible buffer (offscreen frames, screenshots).
    pub copy_to: Option<vk::Buffer>,
    /// Leave the image in PRESENT_SRC (a swapchain image); otherwise it stays a copy
    /// source (offscreen targets, whose next frame starts from COPY).
    pub present: bool,
}

/// Semaphores a frame's submission waits for and signals: the swapchain image's
/// acquire and the hand-over to presentation (none for offscreen frames).
#[derive(Default, Clone, Copy)]
pub struct FrameSync<'a> {
    pub wait: &'a [vk::SemaphoreSubmitInfo<'a>],
    pub signal: &'a [vk::SemaphoreSubmitInfo<'a>],
}

/// Frame statistics of one draw.
#[derive(Clone, Copy, Debug, Default)]
pub struct DrawStats {
    pub draw_calls: u64,
    /// Triangles rasterized (ray-cast blocks not included).
    pub triangles: u64,
    /// Blocks drawn by the ray-caster.
    pub raycast_blocks: u64,
    /// Parts left out of the blocks drawn as triangles (`DrawBlock::hidden_parts`).
    pub hidden_parts: u64,
    /// GPU time of the frame's commands (timestamps), when the queue has them.
    pub gpu_ms: Option<f64>,
    /// The raw begin and end timestamps behind `gpu_ms`.
    pub gpu_ticks: Option<[u64; 2]>,
    /// When the submission asked for the queue's lock and got it.
    pub queue_lock: Option<(std::time::Instant, std::time::Instant)>,
    /// When the draw thread started and stopped waiting for this frame's fence.
    pub waited: Option<(std::time::Instant, std::time::Instant)>,
    /// How long the draw thread was blocked waiting for this frame to finish (its
    /// frames in flight ahead of it and, on a shared queue, error updates).
    pub wait_ms: f64,
}

/// Pipelines and per-frame state of the block renderer. Owned by the draw thread.
pub struct BlocksRenderer {
    device: Arc<Device>,
    pub layout: BlockLayout,
    pub mesh: BlockMesh,
    set_layout: DescriptorSetLayout,
    pipeline_layout: PipelineLayout,
    color_format: vk::Format,
    /// Whether the terrain has a base and a detail texture (fixed per renderer).
    textures: (bool, bool),
    /// Voids are drawn as holes: forward shading only (a hole must show what is behind
    /// it, which the deferred pass's one depth per pixel cannot).
    holes: bool,
    /// Terrain pipelines made so far, one per shading variant (made on first use).
    terrain_pipelines: Vec<(TerrainVariant, GraphicsPipeline)>,
    /// Deferred shading's first pass: the blocks, depth only, the embedding margin
    /// clipped (None without shaderClipDistance: frames are then shaded forward).
    depth_pipeline: Option<GraphicsPipeline>,
    /// Ray-cast blocks' depth pass (made beside `depth_pipeline`).
    raycast_pipeline: Option<GraphicsPipeline>,
    /// Every block's height range (ray-cast blocks' boxes).
    ranges: raycast::BlockRanges,
    sky_pipeline: GraphicsPipeline,
    pool: DescriptorPool,
    /// One uniform buffer and descriptor set per frame in flight.
    sets: Vec<vk::DescriptorSet>,
    uniforms: Vec<Buffer>,
    commands: CommandPool,
    /// Offscreen frames in flight (bench, render, tests); the viewer presents through
    /// its swapchain instead.
    offscreen: Vec<OffscreenSlot>,
    /// Sun visibility and ambient occlusion, sampled by the terrain shader.
    lighting: LightingMap,
}

/// The runs `(first part, parts)` of consecutive parts of `0..parts` whose bit in
/// `hidden` is clear.
pub fn visible_runs(hidden: u16, parts: u32) -> impl Iterator<Item = (u32, u32)> {
    let mut p = 0;
    std::iter::from_fn(move || {
        while p < parts && hidden & (1 << p) != 0 {
            p += 1;
        }
        let first = p;
        while p < parts && hidden & (1 << p) == 0 {
            p += 1;
        }
        (p > first).then_some((first, p - first))
    })
}

/// Records a block's parts whose bits in `hidden` are clear, one indexed draw per run of
/// them (each part is one range of the mesh's indices); returns the parts left out, the
/// triangles drawn and the draws.
///
/// # Safety
/// `cmd` is recording inside a rendering, with `mesh`'s buffers bound and the block's
/// push constants set.
pub(crate) unsafe fn draw_visible_parts(
    d: &ash::Device,
    cmd: vk::CommandBuffer,
    mesh: &BlockMesh,
    layout: &BlockLayout,
    hidden: u16,
) -> [u64; 3] {
    let parts = layout.parts_per_side().pow(2);
    let part_indices = mesh.index_count / parts;
    let mut drawn = [u64::from((hidden & layout.all_parts()).count_ones()), 0, 0];
    for (first, count) in visible_runs(hidden, parts) {
        // SAFETY: the caller's recording state (see above); the range lies in the mesh.
        unsafe { d.cmd_draw_indexed(cmd, count * part_indices, 1, first * part_indices, 0, 0) };
        drawn[1] += u64::from(count) * layout.triangles_per_part();
        drawn[2] += 1;
    }
    drawn
}

/// One offscreen frame in flight: its commands, fence and timestamps.
struct OffscreenSlot {
    cmd: vk::CommandBuffer,
    fence: Fence,
    /// Start and end timestamps of the frame, when the queue has them.
    timer: Option<FrameTimer>,
    /// The frame submitted from this slot and not yet waited for.
    pending: Option<DrawStats>,
}

impl BlocksRenderer {
    /// A renderer of `hf` (on the GPU as `terrain`) into `color_format` targets, lit by
    /// `sun` (`None`: no shadows or occlusion).
    pub fn new(
        device: &Arc<Device>,
        hf: &Heightfield,
        terrain: &TerrainGpu,
        block_layout: BlockLayout,
        color_format: vk::Format,
        frames_in_flight: usize,
        sun: Option<Sun>,
    ) -> VkResult<Self> {
        let lighting = LightingMap::new(device, hf, terrain, sun)?;
        let stages = vk::ShaderStageFlags::VERTEX | vk::ShaderStageFlags::FRAGMENT;
        let sampler = vk::DescriptorType::COMBINED_IMAGE_SAMPLER;
        let set_layout = DescriptorSetLayout::new(
            device,
            &[
                (layout::TERRAIN_BINDING_HEIGHTS, sampler, stages),
                (layout::TERRAIN_BINDING_FRAME, vk::DescriptorType::UNIFORM_BUFFER, stages),
                (layout::TERRAIN_BINDING_BASE, sampler, vk::ShaderStageFlags::FRAGMENT),
                (layout::TERRAIN_BINDING_DETAIL, sampler, vk::ShaderStageFlags::FRAGMENT),
                (layout::TERRAIN_BINDING_GRADIENTS, sampler, vk::ShaderStageFlags::FRAGMENT),
                (layout::TERRAIN_BINDING_LIGHTING, sampler, vk::ShaderStageFlags::FRAGMENT),
                (layout::TERRAIN_BINDING_DEPTH, sampler, vk::ShaderStageFlags::FRAGMENT),
                (layout::TERRAIN_BINDING_MINMAX, sampler, stages),
            ],
        )?;
        let pipeline_layout = PipelineLayout::new(
            device,
            &set_layout,
            std::mem::size_of::<BlockPush>() as u32,
            vk::ShaderStageFlags::VERTEX,
        )?;
        let sky_pipeline = sky_pipeline(device, &pipeline_layout, color_format)?;
        let depth_pipeline = depth_pass_pipeline(device, &pipeline_layout, shaders::TERRAIN_DEPTH_VERT)?;
        let raycast_pipeline = (depth_pipeline.as_ref())
            .map(|_| raycast_pipeline(device, &pipeline_layout, (shaders::RAYCAST_VERT, shaders::RAYCAST_FRAG)))
            .transpose()?;
        let n = frames_in_flight.max(1) as u32;
        let pool = DescriptorPool::new(device, n, &[(sampler, 7 * n), (vk::DescriptorType::UNIFORM_BUFFER, n)])?;
        let ubo_size = std::mem::size_of::<FrameUniforms>() as u64;
        let mut sets = Vec::new();
        let mut uniforms = Vec::new();
        for i in 0..n {
            let set = pool.allocate(&set_layout)?;
            let ubo = Buffer::new(
                device,
                &format!("frame uniforms {i}"),
                ubo_size,
                vk::BufferUsageFlags::UNIFORM_BUFFER,
                gpu_allocator::MemoryLocation::CpuToGpu,
            )?;
            pool.write(
                set,
                &[
                    (layout::TERRAIN_BINDING_HEIGHTS, terrain.heights.view, terrain.nearest.handle),
                    (layout::TERRAIN_BINDING_BASE, terrain.textures.base.view, terrain.linear.handle),
                    (layout::TERRAIN_BINDING_DETAIL, terrain.textures.detail.view, terrain.linear.handle),
                    (layout::TERRAIN_BINDING_GRADIENTS, terrain.gradients.view, terrain.nearest.handle),
                    (layout::TERRAIN_BINDING_LIGHTING, lighting.image.view, lighting.sampler.handle),
                    // A placeholder until the first frame writes its depth image here
                    // (`submit_frame`).
                    (layout::TERRAIN_BINDING_DEPTH, terrain.heights.view, terrain.nearest.handle),
                    (layout::TERRAIN_BINDING_MINMAX, terrain.minmax.view, terrain.nearest.handle),
                ],
                &[(layout::TERRAIN_BINDING_FRAME, ubo.handle, ubo_size)],
            );
            sets.push(set);
            uniforms.push(ubo);
        }
        let commands = CommandPool::new(device, device.draw_queue.family)?;
        let offscreen = (0..n)
            .map(|_| {
                Ok(OffscreenSlot {
                    cmd: commands.allocate()?,
                    fence: Fence::new(device, true)?,
                    timer: FrameTimer::new(device)?,
                    pending: None,
                })
            })
            .collect::<VkResult<Vec<_>>>()?;
        let mut renderer = BlocksRenderer {
            device: device.clone(),
            layout: block_layout,
            mesh: BlockMesh::new(device, block_layout.k())?,
            set_layout,
            pipeline_layout,
            color_format,
            textures: (terrain.textures.has_base, terrain.textures.has_detail),
            holes: hf.void_mask.is_some(),
            terrain_pipelines: Vec::new(),
            depth_pipeline,
            raycast_pipeline,
            ranges: raycast::BlockRanges::of(hf, &block_layout),
            sky_pipeline,
            pool,
            sets,
            uniforms,
            commands,
            offscreen,
            lighting,
        };
        // The default shading's pipelines now, so that the first frame does not compile them.
        renderer.frame_pipelines(&Shading::default(), true)?;
        Ok(renderer)
    }

    /// The pipelines of a frame drawn with `shading`.
    /// `depth_precise`: the depth can stand for the position (see [`depth_precise_enough`]).
    fn frame_pipelines(&mut self, shading: &Shading, depth_precise: bool) -> VkResult<FramePipelines> {
        // Deferred needs the depth pass, which needs clip distances.
        let depth_pass = (self.depth_pipeline.as_ref().map(|p| p.handle))
            .filter(|_| shading.deferred() && depth_precise && !self.holes);
        let variant = TerrainVariant {
            normals: shading.normals,
            colour_by_lod: shading.colour_by_lod,
            wireframe: shading.wireframe && self.device.features.wireframe,
            deferred: depth_pass.is_some(),
        };
        let terrain = self.terrain_pipeline(variant)?;
        let raycast = (self.raycast_pipeline.as_ref().map(|p| p.handle))
            .filter(|_| depth_pass.is_some() && shading.raycast != Raycast::Off);
        Ok(match depth_pass {
            Some(depth) => FramePipelines { blocks: depth, raycast, shade: Some(terrain) },
            None => FramePipelines { blocks: terrain, raycast: None, shade: None },
        })
    }

    /// The terrain shading pipeline of `variant`, made the first time it is asked for (a
    /// few tens of milliseconds on lavapipe; the viewer's toggles each make one).
    fn terrain_pipeline(&mut self, variant: TerrainVariant) -> VkResult<vk::Pipeline> {
        if let Some((_, p)) = self.terrain_pipelines.iter().find(|(v, _)| *v == variant) {
            return Ok(p.handle);
        }
        let (base, detail) = self.textures;
        let specialization = [
            (layout::SPEC_NORMALS_FROM_HEIGHTS, variant.normals == NormalSource::Heights),
            (layout::SPEC_BASE_TEXTURE, base),
            (layout::SPEC_DETAIL_TEXTURE, detail),
            (layout::SPEC_COLOUR_BY_LOD, variant.colour_by_lod),
            (layout::SPEC_HOLES, self.holes),
        ];
        let desc = if variant.deferred {
            // Over the whole target, with the depth attached read-only (as the viewer's
            // panel, drawn in the same rendering, expects).
            GraphicsPipelineDesc {
                vert: shaders::FULLSCREEN_VERT,
                frag: Some(shaders::SHADE_FRAG),
                rasterizer_discard: false,
                vertex_attribute: None,
                color_format: Some(self.color_format),
                depth_format: Some(DEPTH_FORMAT),
                depth: DepthMode::Off,
                polygon_mode: vk::PolygonMode::FILL,
                cull_back: false,
                layout: &self.pipeline_layout,
                specialization: &specialization,
            }
        } else {
            GraphicsPipelineDesc {
                vert: shaders::TERRAIN_VERT,
                frag: Some(shaders::TERRAIN_FRAG),
                rasterizer_discard: false,
                vertex_attribute: Some((2, vk::Format::R8G8_UINT)),
                color_format: Some(self.color_format),
                depth_format: Some(DEPTH_FORMAT),
                depth: DepthMode::TestWrite,
                polygon_mode: if variant.wireframe { vk::PolygonMode::LINE } else { vk::PolygonMode::FILL },
                // A heightfield is seen from above only: culling its underside lets a crack
                // show the background instead of hiding behind back faces, and saves work.
                cull_back: true,
                layout: &self.pipeline_layout,
                specialization: &specialization,
            }
        };
        let pipeline = GraphicsPipeline::new(&self.device, &desc)?;
        let handle = pipeline.handle;
        self.terrain_pipelines.push((variant, pipeline));
        Ok(handle)
    }

    fn frame_uniforms(&self, hf: &Heightfield, terrain: &TerrainGpu, cam: &Camera, shading: &Shading) -> FrameUniforms {
        let vp = cam.view_proj();
        let sky = if shading.sky { 1.0 } else { 0.0 };
        let horizon = if shading.sky { SKY_HORIZON } else { shading.background };
        // Without a sun (no shadows) the light still comes from the default direction.
        let light = self.lighting.sun().unwrap_or(Sun::DEFAULT).direction();
        FrameUniforms {
            view_proj: vp.to_cols_array_2d(),
            // Inverted in f64: the columns the sky and the deferred pass use for directions
            // stay exact rotations beside the large translation column.
            inv_view_proj: vp.as_dmat4().inverse().as_mat4().to_cols_array_2d(),
            camera_fog: [cam.position.x, cam.position.y, cam.position.z, shading.fog_density],
            terrain: [
                crate::gpu::layout::ramp_top(hf.georef.absolute_heights),
                hf.height_scale,
                terrain.raw_range[0] * hf.height_scale,
                terrain.raw_range[1] * hf.height_scale,
            ],
            spacing: [hf.spacing.x, hf.spacing.z, 0.0, 0.0],
            light: [light.x, light.y, light.z, 0.25],
            texturing: [
                shading.detail_tiling,
                shading.detail_weight,
                terrain.gradient_scale(hf),
                terrain.sea_level(hf),
            ],
            extent: [hf.width as i32, hf.height as i32, hf.grid()[0] as i32, self.layout.k() as i32],
            flags: [(hf.format == crate::lod::heightfield::HeightFormat::Unorm16) as i32, 0, 0, 0],
            sky_zenith: [SKY_ZENITH[0], SKY_ZENITH[1], SKY_ZENITH[2], sky],
            sky_horizon: [horizon[0], horizon[1], horizon[2], 1.0],
            anchor: [0; 4],
        }
    }

    /// Records every block and the sky into `cmd`, inside dynamic rendering on `color`:
    /// forward, one rendering; deferred, the blocks' depth, then the shading pass.
    #[allow(clippy::too_many_arguments)]
    fn record(
        &self,
        slot: usize,
        cmd: vk::CommandBuffer,
        pipelines: FramePipelines,
        color_view: vk::ImageView,
        depth: &Image,
        extent: vk::Extent2D,
        blocks: &[DrawBlock],
        shading: &Shading,
        choice: &raycast::Choice,
        clear: [f32; 3],
        overlay: Option<&mut dyn FnMut(vk::CommandBuffer)>,
    ) -> DrawStats {
        let d = &self.device.raw;
        let deferred = pipelines.shade.is_some();
        let color_att = [vk::RenderingAttachmentInfo::default()
            .image_view(color_view)
            .image_layout(vk::ImageLayout::COLOR_ATTACHMENT_OPTIMAL)
            // The shading pass writes every pixel.
            .load_op(if deferred { vk::AttachmentLoadOp::DONT_CARE } else { vk::AttachmentLoadOp::CLEAR })
            .store_op(vk::AttachmentStoreOp::STORE)
            .clear_value(vk::ClearValue {
                color: vk::ClearColorValue { float32: [clear[0], clear[1], clear[2], 1.0] },
            })];
        let depth_att = vk::RenderingAttachmentInfo::default()
            .image_view(depth.view)
            .image_layout(vk::ImageLayout::DEPTH_ATTACHMENT_OPTIMAL)
            .load_op(vk::AttachmentLoadOp::CLEAR)
            .store_op(if deferred { vk::AttachmentStoreOp::STORE } else { vk::AttachmentStoreOp::DONT_CARE })
            .clear_value(vk::ClearValue { depth_stencil: vk::ClearDepthStencilValue { depth: 0.0, stencil: 0 } });
        let area = vk::Rect2D { offset: vk::Offset2D::default(), extent };
        let rendering = vk::RenderingInfo::default().render_area(area).layer_count(1).depth_attachment(&depth_att);
        let rendering = if deferred { rendering } else { rendering.color_attachments(&color_att) };
        let viewport = vk::Viewport {
            x: 0.0,
            y: 0.0,
            width: extent.width as f32,
            height: extent.height as f32,
            min_depth: 0.0,
            max_depth: 1.0,
        };
        let mut stats = DrawStats::default();
        // SAFETY: `cmd` is recording on this thread; every bound object outlives the
        // submission (the caller waits before reuse or drop).
        unsafe {
            d.cmd_begin_rendering(cmd, &rendering);
            d.cmd_set_viewport(cmd, 0, &[viewport]);
            d.cmd_set_scissor(cmd, 0, &[area]);
            d.cmd_bind_descriptor_sets(
                cmd,
                vk::PipelineBindPoint::GRAPHICS,
                self.pipeline_layout.handle,
                0,
                &[self.sets[slot]],
                &[],
            );
            d.cmd_bind_pipeline(cmd, vk::PipelineBindPoint::GRAPHICS, pipelines.blocks);
            d.cmd_bind_vertex_buffers(cmd, 0, &[self.mesh.vertices.handle], &[0]);
            d.cmd_bind_index_buffer(cmd, self.mesh.indices.handle, 0, self.mesh.index_type);
            // Decided once per block: `auto` projects the block's box.
            let cast: Vec<bool> = blocks.iter().map(|b| pipelines.raycast.is_some() && choice.casts(b)).collect();
            let cast_blocks = || blocks.iter().zip(&cast).filter(|(_, &c)| c).map(|(b, _)| b);
            let push = |b: &DrawBlock| {
                let push = block_push(&self.layout, b);
                d.cmd_push_constants(
                    cmd,
                    self.pipeline_layout.handle,
                    vk::ShaderStageFlags::VERTEX,
                    0,
                    bytemuck::bytes_of(&push),
                );
            };
            for b in blocks.iter().zip(&cast).filter(|(_, &c)| !c).map(|(b, _)| b) {
                push(b);
                // Occlusion culling's hidden parts left out.
                let [hidden, triangles, draws] = draw_visible_parts(d, cmd, &self.mesh, &self.layout, b.hidden_parts);
                stats.hidden_parts += hidden;
                stats.triangles += triangles;
                stats.draw_calls += draws;
            }
            if let Some(raycast) = pipelines.raycast {
                // The outer ring of every ray-cast block as triangles (see BlockMesh).
                for b in cast_blocks() {
                    push(b);
                    d.cmd_draw_indexed(cmd, self.mesh.ring_count, 1, self.mesh.ring_first, 0, 0);
                    stats.triangles += self.mesh.ring_count as u64 / 3;
                }
                // Then the rays, after every rasterized triangle: their depth writes
                // disable early depth tests, so the nearer terrain already in the depth
                // image rejects what it hides only after the ray has run.
                d.cmd_bind_pipeline(cmd, vk::PipelineBindPoint::GRAPHICS, raycast);
                for b in cast_blocks() {
                    push(b);
                    // The box: 6 faces of 2 triangles, made by raycast.vert.
                    d.cmd_draw(cmd, 36, 1, 0, 0);
                    stats.raycast_blocks += 1;
                }
            }
            if let Some(shade) = pipelines.shade {
                begin_shading_pass(d, cmd, depth, area, &color_att);
                d.cmd_bind_pipeline(cmd, vk::PipelineBindPoint::GRAPHICS, shade);
                d.cmd_draw(cmd, 3, 1, 0, 0);
            } else if shading.sky {
                // The sky last, only where no terrain was drawn (depth still at the far
                // plane): hidden sky pixels are never shaded.
                d.cmd_bind_pipeline(cmd, vk::PipelineBindPoint::GRAPHICS, self.sky_pipeline.handle);
                d.cmd_draw(cmd, 3, 1, 0, 0);
            }
        }
        // Drawn over everything in the same rendering (the viewer's panel).
        if let Some(draw) = overlay {
            draw(cmd);
        }
        // SAFETY: as above; the rendering begun above is still open.
        unsafe {
            d.cmd_end_rendering(cmd);
        }
        stats.draw_calls += stats.raycast_blocks + (deferred || shading.sky) as u64;
        stats
    }

    /// Records one whole frame into `cmd` (begun, not ended): the attachments made
    /// writable, the blocks and the sky, then the copy to host memory and/or the
    /// hand-over to presentation. The one frame recording of the viewer (swapchain) and
    /// of offscreen frames (bench, render, tests). `overlay` records more drawing into
    /// the same rendering, after the terrain and the sky.
    #[allow(clippy::too_many_arguments)]
    fn record_frame(
        &self,
        slot: usize,
        cmd: vk::CommandBuffer,
        pipelines: FramePipelines,
        dest: &FrameDest,
        blocks: &[DrawBlock],
        shading: &Shading,
        choice: &raycast::Choice,
        overlay: Option<&mut dyn FnMut(vk::CommandBuffer)>,
    ) -> DrawStats {
        let d = &self.device.raw;
        // SAFETY: `cmd` is recording on this thread; the caller keeps every image and
        // buffer alive until the submission completes.
        unsafe { attachment_barriers(d, cmd, dest.image, dest.last_use, dest.depth) };
        let clear = if shading.sky { SKY_HORIZON } else { shading.background };
        let stats = self.record(
            slot,
            cmd,
            pipelines,
            dest.view,
            dest.depth,
            dest.extent,
            blocks,
            shading,
            choice,
            clear,
            overlay,
        );
        let rendered = (
            vk::PipelineStageFlags2::COLOR_ATTACHMENT_OUTPUT,
            vk::AccessFlags2::COLOR_ATTACHMENT_WRITE,
            vk::ImageLayout::COLOR_ATTACHMENT_OPTIMAL,
        );
        let copied = crate::vk::COPY_SOURCE;
        let present = (vk::PipelineStageFlags2::NONE, vk::AccessFlags2::NONE, vk::ImageLayout::PRESENT_SRC_KHR);
        // SAFETY: as above.
        unsafe {
            let mut last = rendered;
            if let Some(buffer) = dest.copy_to {
                image_barrier(d, cmd, dest.image, COLOR_RANGE, last, copied);
                crate::vk::copy_image_to_host(d, cmd, dest.image, dest.extent, buffer);
                last = copied;
            }
            if dest.present {
                image_barrier(d, cmd, dest.image, COLOR_RANGE, last, present);
            }
        }
        stats
    }

    /// Redraws the lighting map for `sun` (`None`: no shadows or occlusion); frames
    /// recorded from now on use it.
    pub fn set_sun(&mut self, hf: &Heightfield, sun: Option<Sun>) -> VkResult<()> {
        self.lighting.set_sun(&LightingSource::whole(hf), sun)
    }

    /// Redraws the lighting map over `hf` at its (new) height scale.
    pub fn redraw_lighting(&mut self, hf: &Heightfield) -> VkResult<()> {
        self.lighting.redraw(&LightingSource::whole(hf))
    }

    /// The lighting map (tests read it back).
    pub fn lighting(&self) -> &LightingMap {
        &self.lighting
    }

    /// Writes the uniforms of `slot`. Only call when no pending frame uses that slot.
    pub fn set_frame(
        &mut self,
        slot: usize,
        hf: &Heightfield,
        terrain: &TerrainGpu,
        cam: &Camera,
        shading: &Shading,
    ) -> VkResult<()> {
        let u = self.frame_uniforms(hf, terrain, cam, shading);
        self.uniforms[slot].mapped_mut()?[..std::mem::size_of::<FrameUniforms>()]
            .copy_from_slice(bytemuck::bytes_of(&u));
        Ok(())
    }

    /// Renders one frame into `target` (copying it to host memory, the headless stand-in
    /// for presenting), waits for it, and returns it as RGBA8 (sRGB) with the stats (the
    /// GPU time from timestamps when the device has them).
    pub fn render_offscreen(
        &mut self,
        hf: &Heightfield,
        terrain: &TerrainGpu,
        target: &Target,
        cam: &Camera,
        blocks: &[DrawBlock],
        shading: &Shading,
    ) -> VkResult<(Vec<u8>, DrawStats)> {
        self.submit_offscreen(0, hf, terrain, target, cam, blocks, shading, true)?;
        let stats = self.wait_frame(0)?.expect("a frame was just submitted");
        Ok((target.pixels()?, stats))
    }

    /// Offscreen frames that can be in flight at once (one per uniform slot).
    pub fn frames_in_flight(&self) -> usize {
        self.offscreen.len()
    }

    /// Records and submits a frame from slot `slot` into `target` (which no other
    /// pending frame may use), after waiting for the slot's previous frame, whose stats
    /// are returned. With `read_back` the frame ends by copying its image into the
    /// target's readback buffer ([`Target::pixels`]); without, it ends as a window's
    /// frame does, drawn (the copy costs a frame's worth of bandwidth, and on lavapipe
    /// the queue's thread copies on the CPU). Nothing waits for the new frame: see
    /// [`Self::wait_frame`].
    #[allow(clippy::too_many_arguments)]
    pub fn submit_offscreen(
        &mut self,
        slot: usize,
        hf: &Heightfield,
        terrain: &TerrainGpu,
        target: &Target,
        cam: &Camera,
        blocks: &[DrawBlock],
        shading: &Shading,
        read_back: bool,
    ) -> VkResult<Option<DrawStats>> {
        let dest = FrameDest {
            image: target.color.handle,
            view: target.color.view,
            extent: vk::Extent2D { width: target.width, height: target.height },
            depth: &target.depth,
            // The target's previous frame ended with the copy or with its drawing.
            last_use: (
                vk::PipelineStageFlags2::COPY | vk::PipelineStageFlags2::COLOR_ATTACHMENT_OUTPUT,
                vk::AccessFlags2::TRANSFER_READ | vk::AccessFlags2::COLOR_ATTACHMENT_WRITE,
            ),
            copy_to: read_back.then_some(target.readback.handle),
            present: false,
        };
        target.set_read_back(read_back);
        self.submit_frame(slot, hf, terrain, &dest, cam, blocks, shading, None, FrameSync::default())
    }

    /// The one frame submission of every command (view, bench, render, tests): waits for
    /// the previous frame of `slot` (its stats are returned), writes the slot's uniforms,
    /// records the frame into `dest` between the slot's timestamps, and submits it on the
    /// draw queue with `sync`'s semaphores, fenced by the slot. Nothing waits for the new
    /// frame: see [`Self::wait_frame`].
    #[allow(clippy::too_many_arguments)]
    pub fn submit_frame(
        &mut self,
        slot: usize,
        hf: &Heightfield,
        terrain: &TerrainGpu,
        dest: &FrameDest,
        cam: &Camera,
        blocks: &[DrawBlock],
        shading: &Shading,
        overlay: Option<&mut dyn FnMut(vk::CommandBuffer)>,
        sync: FrameSync,
    ) -> VkResult<Option<DrawStats>> {
        let previous = self.wait_frame(slot)?;
        self.set_frame(slot, hf, terrain, cam, shading)?;
        let pipelines = self.frame_pipelines(shading, depth_precise_enough(hf, terrain, cam))?;
        // Rewritten every frame, forward ones included: the slot's set is idle (waited
        // for above), a target's depth image may be gone since the last frame (the
        // viewer's is replaced on resize), and lavapipe reads every descriptor of a set
        // when it is bound, used or not.
        self.pool.write_in_layout(
            self.sets[slot],
            &[(layout::TERRAIN_BINDING_DEPTH, dest.depth.view, terrain.nearest.handle)],
            vk::ImageLayout::DEPTH_READ_ONLY_OPTIMAL,
            &[],
        );
        let d = self.device.raw.clone();
        let cmd = self.offscreen[slot].cmd;
        // SAFETY: the slot's previous submission finished (waited for above).
        unsafe {
            begin_one_time(&d, cmd)?;
            if let Some(t) = &self.offscreen[slot].timer {
                t.begin(&d, cmd);
            }
        }
        let choice = self.raycast_choice(hf, cam, shading.raycast);
        let stats = self.record_frame(slot, cmd, pipelines, dest, blocks, shading, &choice, overlay);
        drop(choice);
        // SAFETY: as above.
        unsafe {
            if let Some(t) = &self.offscreen[slot].timer {
                t.end(&d, cmd);
            }
            d.end_command_buffer(cmd).vk("vkEndCommandBuffer")?;
        }
        let s = &mut self.offscreen[slot];
        s.fence.reset()?;
        let cmds = [vk::CommandBufferSubmitInfo::default().command_buffer(cmd)];
        let submit = [vk::SubmitInfo2::default()
            .wait_semaphore_infos(sync.wait)
            .command_buffer_infos(&cmds)
            .signal_semaphore_infos(sync.signal)];
        let (asked, got) = self.device.draw_queue.submit_timed(&self.device, &submit, s.fence.handle)?;
        let mut stats = stats;
        stats.queue_lock = Some((asked, got));
        s.pending = Some(stats);
        Ok(previous)
    }

    /// Which blocks a frame of `hf` seen by `cam` ray-casts with `mode` (the bench counts
    /// their rays with the same choice).
    /// A camera that can see the surface from below (under it, or beyond the terrain's
    /// edge lower than its top, looking in through the cut edge) sees through the
    /// rasterizer's culled undersides, which the rays do not reproduce: no block is
    /// ray-cast then.
    pub fn raycast_choice<'a>(&'a self, hf: &'a Heightfield, cam: &'a Camera, mode: Raycast) -> raycast::Choice<'a> {
        let p = cam.position;
        let (wx, wz) = hf.world_extent();
        let beyond = p.x < 0.0 || p.z < 0.0 || p.x > wx || p.z > wz;
        let under = p.y < hf.surface_height(p.x, p.z) || (beyond && p.y < self.ranges.top() * hf.height_scale);
        let mode = if under { Raycast::Off } else { mode };
        raycast::Choice::in_memory((mode, cam), &self.layout, hf, &self.ranges, self.mesh.ring_count as u64 / 3)
    }

    /// Stats of the frame submitted from `slot` and not yet waited for (its GPU time
    /// is known only once [`Self::wait_frame`] returns it).
    pub fn pending(&self, slot: usize) -> Option<DrawStats> {
        self.offscreen[slot].pending
    }

    /// Waits for the frame pending in `slot`, if any, and returns its stats with the GPU
    /// time and how long this thread was blocked waiting for it.
    pub fn wait_frame(&mut self, slot: usize) -> VkResult<Option<DrawStats>> {
        let s = &mut self.offscreen[slot];
        let Some(mut stats) = s.pending.take() else { return Ok(None) };
        let t = std::time::Instant::now();
        s.fence.wait(u64::MAX)?;
        let done = std::time::Instant::now();
        stats.wait_ms = (done - t).as_secs_f64() * 1e3;
        stats.waited = Some((t, done));
        if let Some(t) = &s.timer {
            let (ticks, ms) = t.read()?;
            stats.gpu_ticks = Some(ticks);
            stats.gpu_ms = Some(ms);
        }
        Ok(Some(stats))
    }
}

impl BlocksRenderer {
    /// Test hook: the world position the vertex shader gives every vertex of `blocks`
    /// (`k * k` per block, row-major), computed by glsl/capture.vert with the same
    /// placement code as the terrain pipeline. Needs vertexPipelineStoresAndAtomics.
    pub fn capture_vertices(
        &mut self,
        hf: &Heightfield,
        terrain: &TerrainGpu,
        cam: &Camera,
        blocks: &[DrawBlock],
    ) -> VkResult<Vec<[f32; 4]>> {
        let device = self.device.clone();
        if !device.features.vertex_stores {
            return Err(crate::vk::VkError::Setup("vertex capture needs vertexPipelineStoresAndAtomics".into()));
        }
        let k = self.layout.k() as usize;
        let vertex = vk::ShaderStageFlags::VERTEX;
        let set_layout = DescriptorSetLayout::new(
            &device,
            &[
                (layout::TERRAIN_BINDING_HEIGHTS, vk::DescriptorType::COMBINED_IMAGE_SAMPLER, vertex),
                (layout::TERRAIN_BINDING_FRAME, vk::DescriptorType::UNIFORM_BUFFER, vertex),
                (layout::CAPTURE_BINDING_POSITIONS, vk::DescriptorType::STORAGE_BUFFER, vertex),
            ],
        )?;
        let pipeline_layout =
            PipelineLayout::new(&device, &set_layout, std::mem::size_of::<BlockPush>() as u32, vertex)?;
        let pipeline = GraphicsPipeline::new(
            &device,
            &GraphicsPipelineDesc::vertex_capture(shaders::CAPTURE_VERT, &pipeline_layout),
        )?;
        let pool = DescriptorPool::new(
            &device,
            1,
            &[
                (vk::DescriptorType::COMBINED_IMAGE_SAMPLER, 1),
                (vk::DescriptorType::UNIFORM_BUFFER, 1),
                (vk::DescriptorType::STORAGE_BUFFER, 1),
            ],
        )?;
        let set = pool.allocate(&set_layout)?;
        let bytes = (blocks.len().max(1) * k * k * 16) as u64;
        let positions = Buffer::new(
            &device,
            "captured vertices",
            bytes,
            vk::BufferUsageFlags::STORAGE_BUFFER,
            gpu_allocator::MemoryLocation::GpuToCpu,
        )?;
        self.set_frame(0, hf, terrain, cam, &Shading::default())?;
        let ubo_size = std::mem::size_of::<FrameUniforms>() as u64;
        pool.write(
            set,
            &[(layout::TERRAIN_BINDING_HEIGHTS, terrain.heights.view, terrain.nearest.handle)],
            &[(layout::TERRAIN_BINDING_FRAME, self.uniforms[0].handle, ubo_size)],
        );
        let storage = [vk::DescriptorBufferInfo { buffer: positions.handle, offset: 0, range: vk::WHOLE_SIZE }];
        let write = vk::WriteDescriptorSet::default()
            .dst_set(set)
            .dst_binding(layout::CAPTURE_BINDING_POSITIONS)
            .descriptor_type(vk::DescriptorType::STORAGE_BUFFER)
            .buffer_info(&storage);
        self.wait_frame(0)?;
        let d = device.raw.clone();
        let cmd = self.offscreen[0].cmd;
        let pushes: Vec<BlockPush> = blocks.iter().map(|b| block_push(&self.layout, b)).collect();
        // SAFETY: the set is new and unused; `cmd` is this renderer's, its last submission
        // completed (fence waited after every use); every object outlives the wait below.
        unsafe {
            d.update_descriptor_sets(&[write], &[]);
            record_capture(
                &d,
                cmd,
                (pipeline.handle, pipeline_layout.handle, set),
                &self.mesh,
                &pushes,
                positions.handle,
            )?;
            d.end_command_buffer(cmd).vk("vkEndCommandBuffer")?;
        }
        let fence = &self.offscreen[0].fence;
        fence.reset()?;
        let cmds = [vk::CommandBufferSubmitInfo::default().command_buffer(cmd)];
        device.draw_queue.submit(&device, &[vk::SubmitInfo2::default().command_buffer_infos(&cmds)], fence.handle)?;
        fence.wait(u64::MAX)?;
        let floats: Vec<f32> = bytemuck::pod_collect_to_vec(&positions.mapped()?[..blocks.len() * k * k * 16]);
        Ok(floats.chunks(4).map(|c| [c[0], c[1], c[2], c[3]]).collect())
    }
}

/// Records the capture hook's draws (one a block, its index as the first instance, which
/// tells the shader where to write) into a 1 x 1 render area, then the barrier that makes
/// the captured positions readable on the host. One copy for both renderers.
///
/// # Safety
/// `cmd` is free for recording on this thread, the set is written, and every handle
/// outlives the caller's wait for the submission.
pub(super) unsafe fn record_capture(
    d: &ash::Device,
    cmd: vk::CommandBuffer,
    (pipeline, pipeline_layout, set): (vk::Pipeline, vk::PipelineLayout, vk::DescriptorSet),
    mesh: &BlockMesh,
    pushes: &[BlockPush],
    positions: vk::Buffer,
) -> VkResult<()> {
    let area = vk::Rect2D { offset: vk::Offset2D::default(), extent: vk::Extent2D { width: 1, height: 1 } };
    begin_one_time(d, cmd)?;
    d.cmd_begin_rendering(cmd, &vk::RenderingInfo::default().render_area(area).layer_count(1));
    d.cmd_set_viewport(
        cmd,
        0,
        &[vk::Viewport { x: 0.0, y: 0.0, width: 1.0, height: 1.0, min_depth: 0.0, max_depth: 1.0 }],
    );
    d.cmd_set_scissor(cmd, 0, &[area]);
    d.cmd_bind_pipeline(cmd, vk::PipelineBindPoint::GRAPHICS, pipeline);
    d.cmd_bind_descriptor_sets(cmd, vk::PipelineBindPoint::GRAPHICS, pipeline_layout, 0, &[set], &[]);
    d.cmd_bind_vertex_buffers(cmd, 0, &[mesh.vertices.handle], &[0]);
    d.cmd_bind_index_buffer(cmd, mesh.indices.handle, 0, mesh.index_type);
    for (i, p) in pushes.iter().enumerate() {
        d.cmd_push_constants(cmd, pipeline_layout, vk::ShaderStageFlags::VERTEX, 0, bytemuck::bytes_of(p));
        d.cmd_draw_indexed(cmd, mesh.index_count, 1, 0, 0, i as u32);
    }
    d.cmd_end_rendering(cmd);
    let written = (vk::PipelineStageFlags2::VERTEX_SHADER, vk::AccessFlags2::SHADER_STORAGE_WRITE);
    host_read_barrier(d, cmd, positions, written);
    Ok(())
}

/// Push constants of one block draw.
fn block_push(layout: &BlockLayout, b: &DrawBlock) -> BlockPush {
    let (ox, oz) = b.origin(layout);
    let c = b.coarser;
    BlockPush {
        block: [ox as i32, oz as i32, b.stride() as i32, b.lod as i32],
        coarser_neighbour_stride: [c[0] as i32, c[1] as i32, c[2] as i32, c[3] as i32],
        morph_edges: b.edge_morph.map(morph_value),
        morph: [morph_value(b.morph), 0.0, 0.0, 0.0],
        corner_raw: b.corner_raw.map(|bits| {
            debug_assert_ne!(bits, crate::lod::block::CORNER_UNRESOLVED, "blocks to draw come from the traversal");
            f32::from_bits(bits)
        }),
        tile: [0; 4],
    }
}

/// Ends the blocks' rendering (depth only) and begins the deferred shading pass's on
/// `color_att`: the blocks' depth is read there both as a texture and as a read-only
/// attachment (the viewer's panel, drawn in the same rendering, has a depth format).
///
/// # Safety
/// `cmd` must be recording inside the blocks' rendering on `depth`, and `depth` and the
/// colour attachments must stay alive until its submission completes.
pub(crate) unsafe fn begin_shading_pass(
    d: &ash::Device,
    cmd: vk::CommandBuffer,
    depth: &Image,
    area: vk::Rect2D,
    color_att: &[vk::RenderingAttachmentInfo],
) {
    let tests = vk::PipelineStageFlags2::EARLY_FRAGMENT_TESTS | vk::PipelineStageFlags2::LATE_FRAGMENT_TESTS;
    let depth_read = vk::RenderingAttachmentInfo::default()
        .image_view(depth.view)
        .image_layout(vk::ImageLayout::DEPTH_READ_ONLY_OPTIMAL)
        .load_op(vk::AttachmentLoadOp::LOAD)
        .store_op(vk::AttachmentStoreOp::NONE);
    let shading_pass = vk::RenderingInfo::default()
        .render_area(area)
        .layer_count(1)
        .color_attachments(color_att)
        .depth_attachment(&depth_read);
    // SAFETY: guaranteed by the caller (see above).
    unsafe {
        d.cmd_end_rendering(cmd);
        image_barrier(
            d,
            cmd,
            depth.handle,
            depth.range(0, 1),
            (tests, vk::AccessFlags2::DEPTH_STENCIL_ATTACHMENT_WRITE, vk::ImageLayout::DEPTH_ATTACHMENT_OPTIMAL),
            (
                tests | vk::PipelineStageFlags2::FRAGMENT_SHADER,
                vk::AccessFlags2::DEPTH_STENCIL_ATTACHMENT_READ | vk::AccessFlags2::SHADER_SAMPLED_READ,
                vk::ImageLayout::DEPTH_READ_ONLY_OPTIMAL,
            ),
        );
        d.cmd_begin_rendering(cmd, &shading_pass);
    }
}

/// Records barriers that make `color` (its old contents discarded) and `depth` writable
/// attachments; `last_use` is the stage and access that last touched `color`.
///
/// # Safety
/// `cmd` must be a command buffer of `d` in the recording state, and both images must
/// stay alive until its submission completes.
pub(crate) unsafe fn attachment_barriers(
    d: &ash::Device,
    cmd: vk::CommandBuffer,
    color: vk::Image,
    last_use: (vk::PipelineStageFlags2, vk::AccessFlags2),
    depth: &Image,
) {
    let fragment_tests = vk::PipelineStageFlags2::EARLY_FRAGMENT_TESTS | vk::PipelineStageFlags2::LATE_FRAGMENT_TESTS;
    let barriers = [
        vk::ImageMemoryBarrier2::default()
            .src_stage_mask(last_use.0)
            .src_access_mask(last_use.1)
            .dst_stage_mask(vk::PipelineStageFlags2::COLOR_ATTACHMENT_OUTPUT)
            .dst_access_mask(vk::AccessFlags2::COLOR_ATTACHMENT_WRITE)
            .old_layout(vk::ImageLayout::UNDEFINED)
            .new_layout(vk::ImageLayout::COLOR_ATTACHMENT_OPTIMAL)
            .image(color)
            .subresource_range(COLOR_RANGE),
        // After the last frame's depth writes, and its shading pass's reads (deferred).
        vk::ImageMemoryBarrier2::default()
            .src_stage_mask(fragment_tests | vk::PipelineStageFlags2::FRAGMENT_SHADER)
            .src_access_mask(vk::AccessFlags2::DEPTH_STENCIL_ATTACHMENT_WRITE)
            .dst_stage_mask(fragment_tests)
            .dst_access_mask(
                vk::AccessFlags2::DEPTH_STENCIL_ATTACHMENT_WRITE | vk::AccessFlags2::DEPTH_STENCIL_ATTACHMENT_READ,
            )
            .old_layout(vk::ImageLayout::UNDEFINED)
            .new_layout(vk::ImageLayout::DEPTH_ATTACHMENT_OPTIMAL)
            .image(depth.handle)
            .subresource_range(depth.range(0, 1)),
    ];
    // SAFETY: guaranteed by the caller (see above).
    unsafe { d.cmd_pipeline_barrier2(cmd, &vk::DependencyInfo::default().image_memory_barriers(&barriers)) };
}

/// The single mip and layer of a colour target.
pub const COLOR_RANGE: vk::ImageSubresourceRange = vk::ImageSubresourceRange {
    aspect_mask: vk::ImageAspectFlags::COLOR,
    base_mip_level: 0,
    level_count: 1,
    base_array_layer: 0,
    layer_count: 1,
};

impl Drop for BlocksRenderer {
    fn drop(&mut self) {
        // Wait for the last frames before the command pool, pipelines and buffers go.
        for s in &self.offscreen {
            let _ = s.fence.wait(u64::MAX);
            self.commands.free(s.cmd);
        }
        let _ = &self.set_layout;
    }
}

#[cfg(test)]
mod tests {
    use super::visible_runs;

    #[test]
    fn visible_runs_skip_hidden_parts() {
        let runs = |h: u16, n: u32| visible_runs(h, n).collect::<Vec<_>>();
        assert_eq!(runs(0, 16), [(0, 16)]);
        assert_eq!(runs(0xffff, 16), []);
        assert_eq!(runs(0b1, 4), [(1, 3)]);
        assert_eq!(runs(0b1000, 4), [(0, 3)]);
        assert_eq!(runs(0b0110, 4), [(0, 1), (3, 1)]);
        assert_eq!(runs(0b1010_0101, 8), [(1, 1), (3, 2), (6, 1)]);
        // Every visible part once, no hidden one, for every mask of 16 parts.
        for h in 0..=u16::MAX {
            let mut covered = 0u32;
            for (first, count) in visible_runs(h, 16) {
                let bits = ((1u32 << count) - 1) << first;
                assert_eq!(covered & bits, 0);
                covered |= bits;
            }
            assert_eq!(covered, !(h as u32) & 0xffff, "mask {h:#x}");
        }
    }
}
