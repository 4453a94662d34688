//! Shader modules, descriptor layouts and pools, pipeline layouts and graphics pipelines
//! (dynamic rendering, dynamic viewport and scissor).

use super::device::Device;
use super::error::{VkError, VkResult, VkResultExt};
use ash::vk;
use std::sync::Arc;

pub struct DescriptorSetLayout {
    device: Arc<Device>,
    pub handle: vk::DescriptorSetLayout,
}

impl DescriptorSetLayout {
    pub fn new(device: &Arc<Device>, bindings: &[(u32, vk::DescriptorType, vk::ShaderStageFlags)]) -> VkResult<Self> {
        let b: Vec<vk::DescriptorSetLayoutBinding> = bindings
            .iter()
            .map(|&(binding, ty, stages)| {
                vk::DescriptorSetLayoutBinding::default()
                    .binding(binding)
                    .descriptor_type(ty)
                    .descriptor_count(1)
                    .stage_flags(stages)
            })
            .collect();
        // SAFETY: `b` outlives the call.
        let handle = unsafe {
            device.raw.create_descriptor_set_layout(&vk::DescriptorSetLayoutCreateInfo::default().bindings(&b), None)
        }
        .vk("vkCreateDescriptorSetLayout")?;
        Ok(DescriptorSetLayout { device: device.clone(), handle })
    }
}

impl Drop for DescriptorSetLayout {
    fn drop(&mut self) {
        // SAFETY: pipelines and sets created from it are gone or idle.
        unsafe { self.device.raw.destroy_descriptor_set_layout(self.handle, None) };
    }
}

pub struct DescriptorPool {
    device: Arc<Device>,
    pub handle: vk::DescriptorPool,
}

impl DescriptorPool {
    pub fn new(device: &Arc<Device>, max_sets: u32, sizes: &[(vk::DescriptorType, u32)]) -> VkResult<Self> {
        let s: Vec<vk::DescriptorPoolSize> =
            sizes.iter().map(|&(ty, n)| vk::DescriptorPoolSize { ty, descriptor_count: n }).collect();
        let info = vk::DescriptorPoolCreateInfo::default().max_sets(max_sets).pool_sizes(&s);
        // SAFETY: `s` outlives the call.
        let handle = unsafe { device.raw.create_descriptor_pool(&info, None) }.vk("vkCreateDescriptorPool")?;
        Ok(DescriptorPool { device: device.clone(), handle })
    }

    pub fn allocate(&self, layout: &DescriptorSetLayout) -> VkResult<vk::DescriptorSet> {
        let layouts = [layout.handle];
        let info = vk::DescriptorSetAllocateInfo::default().descriptor_pool(self.handle).set_layouts(&layouts);
        // SAFETY: the pool is owned by one thread.
        Ok(unsafe { self.device.raw.allocate_descriptor_sets(&info) }.vk("vkAllocateDescriptorSets")?[0])
    }

    /// Writes combined image samplers (read in SHADER_READ_ONLY_OPTIMAL) and uniform
    /// buffers into `set`.
    pub fn write(
        &self,
        set: vk::DescriptorSet,
        images: &[(u32, vk::ImageView, vk::Sampler)],
        buffers: &[(u32, vk::Buffer, u64)],
    ) {
        self.write_in_layout(set, images, vk::ImageLayout::SHADER_READ_ONLY_OPTIMAL, buffers)
    }

    /// [`Self::write`] with the images read in `image_layout`.
    pub fn write_in_layout(
        &self,
        set: vk::DescriptorSet,
        images: &[(u32, vk::ImageView, vk::Sampler)],
        image_layout: vk::ImageLayout,
        buffers: &[(u32, vk::Buffer, u64)],
    ) {
        let image_infos: Vec<[vk::DescriptorImageInfo; 1]> = images
            .iter()
            .map(|&(_, view, sampler)| [vk::DescriptorImageInfo { sampler, image_view: view, image_layout }])
            .collect();
        let buffer_infos: Vec<[vk::DescriptorBufferInfo; 1]> =
            buffers.iter().map(|&(_, buffer, range)| [vk::DescriptorBufferInfo { buffer, offset: 0, range }]).collect();
        let mut writes = Vec::new();
        for (i, &(binding, _, _)) in images.iter().enumerate() {
            writes.push(
                vk::WriteDescriptorSet::default()
                    .dst_set(set)
                    .dst_binding(binding)
                    .descriptor_type(vk::DescriptorType::COMBINED_IMAGE_SAMPLER)
                    .image_info(&image_infos[i]),
            );
        }
        for (i, &(binding, _, _)) in buffers.iter().enumerate() {
            writes.push(
                vk::WriteDescriptorSet::default()
                    .dst_set(set)
                    .dst_binding(binding)
                    .descriptor_type(vk::DescriptorType::UNIFORM_BUFFER)
                    .buffer_info(&buffer_infos[i]),
            );
        }
        // SAFETY: the set is not in use by pending GPU work when it is (re)written.
        unsafe { self.device.raw.update_descriptor_sets(&writes, &[]) };
    }
}

impl Drop for DescriptorPool {
    fn drop(&mut self) {
        // SAFETY: its sets are no longer used by the GPU.
        unsafe { self.device.raw.destroy_descriptor_pool(self.handle, None) };
    }
}

pub struct PipelineLayout {
    device: Arc<Device>,
    pub handle: vk::PipelineLayout,
}

impl PipelineLayout {
    pub fn new(
        device: &Arc<Device>,
        set: &DescriptorSetLayout,
        push_bytes: u32,
        push_stages: vk::ShaderStageFlags,
    ) -> VkResult<Self> {
        let sets = [set.handle];
        let ranges = [vk::PushConstantRange { stage_flags: push_stages, offset: 0, size: push_bytes }];
        let mut info = vk::PipelineLayoutCreateInfo::default().set_layouts(&sets);
        if push_bytes > 0 {
            info = info.push_constant_ranges(&ranges);
        }
        // SAFETY: arrays outlive the call.
        let handle = unsafe { device.raw.create_pipeline_layout(&info, None) }.vk("vkCreatePipelineLayout")?;
        Ok(PipelineLayout { device: device.clone(), handle })
    }
}

impl Drop for PipelineLayout {
    fn drop(&mut self) {
        // SAFETY: pipelines using it are idle.
        unsafe { self.device.raw.destroy_pipeline_layout(self.handle, None) };
    }
}

/// What a graphics pipeline needs; everything else is fixed (triangle lists, one colour
/// attachment, dynamic viewport and scissor).
pub struct GraphicsPipelineDesc<'a> {
    pub vert: &'a [u8],
    /// `None` with `rasterizer_discard` for vertex-only pipelines.
    pub frag: Option<&'a [u8]>,
    pub rasterizer_discard: bool,
    /// Stride and format of a single per-vertex attribute at location 0.
    pub vertex_attribute: Option<(u32, vk::Format)>,
    pub color_format: Option<vk::Format>,
    pub depth_format: Option<vk::Format>,
    pub depth: DepthMode,
    pub polygon_mode: vk::PolygonMode,
    /// Cull back faces. Front faces are clockwise in framebuffer space: the block mesh
    /// winds a -> c -> i counter-clockwise seen from +y, and the projection flips y.
    pub cull_back: bool,
    pub layout: &'a PipelineLayout,
    /// Values of boolean specialization constants (`gpu_layout::SPEC_*` ids), given to
    /// every stage; a stage ignores the ids it does not declare.
    pub specialization: &'a [(u32, bool)],
}

impl<'a> GraphicsPipelineDesc<'a> {
    /// A pass over a whole colour target: one triangle from `vert` (`glsl/pass.vert`,
    /// which only covers the target; the fragment shader reads gl_FragCoord), no depth.
    pub fn fullscreen_pass(
        vert: &'a [u8],
        frag: &'a [u8],
        color_format: vk::Format,
        layout: &'a PipelineLayout,
    ) -> Self {
        GraphicsPipelineDesc {
            vert,
            frag: Some(frag),
            rasterizer_discard: false,
            vertex_attribute: None,
            color_format: Some(color_format),
            depth_format: None,
            depth: DepthMode::Off,
            polygon_mode: vk::PolygonMode::FILL,
            cull_back: false,
            layout,
            specialization: &[],
        }
    }

    /// A vertex-stage-only pass over the block mesh (two `u8` coordinates a vertex) with
    /// rasterization off: tests' capture hooks, which write positions from `vert`.
    pub fn vertex_capture(vert: &'a [u8], layout: &'a PipelineLayout) -> Self {
        GraphicsPipelineDesc {
            vert,
            frag: None,
            rasterizer_discard: true,
            vertex_attribute: Some((2, vk::Format::R8G8_UINT)),
            color_format: None,
            depth_format: None,
            depth: DepthMode::Off,
            polygon_mode: vk::PolygonMode::FILL,
            cull_back: false,
            layout,
            specialization: &[],
        }
    }
}

/// Depth use of a pipeline (reversed Z: nearer is greater, cleared to 0).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum DepthMode {
    Off,
    /// Test and write, nearer wins: the terrain.
    TestWrite,
    /// Drawn only where nothing nearer than the far plane was written, no write: a
    /// background at depth 0 drawn after the scene (the sky), shading only what shows.
    Background,
}

pub struct GraphicsPipeline {
    device: Arc<Device>,
    pub handle: vk::Pipeline,
}

fn shader_module(device: &Device, spirv: &[u8]) -> VkResult<vk::ShaderModule> {
    let words = ash::util::read_spv(&mut std::io::Cursor::new(spirv))
        .map_err(|e| VkError::Setup(format!("bad SPIR-V: {e}")))?;
    // SAFETY: `words` is SPIR-V produced by build.rs.
    unsafe { device.raw.create_shader_module(&vk::ShaderModuleCreateInfo::default().code(&words), None) }
        .vk("vkCreateShaderModule")
}

impl GraphicsPipeline {
    pub fn new(device: &Arc<Device>, d: &GraphicsPipelineDesc<'_>) -> VkResult<Self> {
        let vs = shader_module(device, d.vert)?;
        let fs = d.frag.map(|f| shader_module(device, f)).transpose()?;
        let entry = c"main";
        // Booleans are VkBool32: four bytes each, in order.
        let spec_entries: Vec<vk::SpecializationMapEntry> = (d.specialization.iter().enumerate())
            .map(|(i, &(id, _))| vk::SpecializationMapEntry { constant_id: id, offset: 4 * i as u32, size: 4 })
            .collect();
        let spec_data: Vec<u32> = d.specialization.iter().map(|&(_, on)| on as u32).collect();
        let spec = vk::SpecializationInfo::default().map_entries(&spec_entries).data(bytemuck::cast_slice(&spec_data));
        let stage = |flags, module| {
            let s = vk::PipelineShaderStageCreateInfo::default().stage(flags).module(module).name(entry);
            if spec_entries.is_empty() {
                s
            } else {
                s.specialization_info(&spec)
            }
        };
        let mut stages = vec![stage(vk::ShaderStageFlags::VERTEX, vs)];
        if let Some(fs) = fs {
            stages.push(stage(vk::ShaderStageFlags::FRAGMENT, fs));
        }
        let bindings;
        let attributes;
        let mut vertex_input = vk::PipelineVertexInputStateCreateInfo::default();
        if let Some((stride, format)) = d.vertex_attribute {
            bindings =
                [vk::VertexInputBindingDescription { binding: 0, stride, input_rate: vk::VertexInputRate::VERTEX }];
            attributes = [vk::VertexInputAttributeDescription { location: 0, binding: 0, format, offset: 0 }];
            vertex_input =
                vertex_input.vertex_binding_descriptions(&bindings).vertex_attribute_descriptions(&attributes);
        }
        let assembly =
            vk::PipelineInputAssemblyStateCreateInfo::default().topology(vk::PrimitiveTopology::TRIANGLE_LIST);
        let viewport = vk::PipelineViewportStateCreateInfo::default().viewport_count(1).scissor_count(1);
        let raster = vk::PipelineRasterizationStateCreateInfo::default()
            .rasterizer_discard_enable(d.rasterizer_discard)
            .polygon_mode(d.polygon_mode)
            .cull_mode(if d.cull_back { vk::CullModeFlags::BACK } else { vk::CullModeFlags::NONE })
            .front_face(vk::FrontFace::CLOCKWISE)
            .line_width(1.0);
        let multisample =
            vk::PipelineMultisampleStateCreateInfo::default().rasterization_samples(vk::SampleCountFlags::TYPE_1);
        // Reversed Z: nearer is greater.
        let depth = vk::PipelineDepthStencilStateCreateInfo::default()
            .depth_test_enable(d.depth != DepthMode::Off)
            .depth_write_enable(d.depth == DepthMode::TestWrite)
            .depth_compare_op(if d.depth == DepthMode::Background {
                vk::CompareOp::GREATER_OR_EQUAL
            } else {
                vk::CompareOp::GREATER
            });
        let attachments =
            [vk::PipelineColorBlendAttachmentState::default().color_write_mask(vk::ColorComponentFlags::RGBA)];
        let blend = vk::PipelineColorBlendStateCreateInfo::default().attachments(&attachments);
        let dynamic_states = [vk::DynamicState::VIEWPORT, vk::DynamicState::SCISSOR];
        let dynamic = vk::PipelineDynamicStateCreateInfo::default().dynamic_states(&dynamic_states);
        let color_formats: Vec<vk::Format> = d.color_format.into_iter().collect();
        let mut rendering = vk::PipelineRenderingCreateInfo::default().color_attachment_formats(&color_formats);
        if let Some(df) = d.depth_format {
            rendering = rendering.depth_attachment_format(df);
        }
        let info = vk::GraphicsPipelineCreateInfo::default()
            .stages(&stages)
            .vertex_input_state(&vertex_input)
            .input_assembly_state(&assembly)
            .viewport_state(&viewport)
            .rasterization_state(&raster)
            .multisample_state(&multisample)
            .depth_stencil_state(&depth)
            .color_blend_state(&blend)
            .dynamic_state(&dynamic)
            .layout(d.layout.handle)
            .push_next(&mut rendering);
        // SAFETY: every pointer in `info` refers to locals that outlive the call.
        let result = unsafe { device.raw.create_graphics_pipelines(vk::PipelineCache::null(), &[info], None) };
        // SAFETY: modules are not needed once the pipeline exists (or failed).
        unsafe {
            device.raw.destroy_shader_module(vs, None);
            if let Some(fs) = fs {
                device.raw.destroy_shader_module(fs, None);
            }
        }
        let handle = result.map_err(|(_, e)| e).vk("vkCreateGraphicsPipelines")?[0];
        Ok(GraphicsPipeline { device: device.clone(), handle })
    }
}

impl Drop for GraphicsPipeline {
    fn drop(&mut self) {
        // SAFETY: command buffers using it have completed.
        unsafe { self.device.raw.destroy_pipeline(self.handle, None) };
    }
}
