//! Buffers, images, image views and samplers backed by gpu-allocator.

use super::device::Device;
use super::error::{VkError, VkResult, VkResultExt};
use ash::vk;
use gpu_allocator::vulkan::{Allocation, AllocationCreateDesc, AllocationScheme};
use gpu_allocator::MemoryLocation;
use std::sync::Arc;

fn alloc_err(what: &str, e: impl std::fmt::Display) -> VkError {
    VkError::Alloc { what: what.to_string(), message: e.to_string() }
}

pub struct Buffer {
    device: Arc<Device>,
    pub handle: vk::Buffer,
    allocation: Option<Allocation>,
    pub size: u64,
}

impl Buffer {
    pub fn new(
        device: &Arc<Device>,
        name: &str,
        size: u64,
        usage: vk::BufferUsageFlags,
        location: MemoryLocation,
    ) -> VkResult<Self> {
        let info =
            vk::BufferCreateInfo::default().size(size.max(4)).usage(usage).sharing_mode(vk::SharingMode::EXCLUSIVE);
        // SAFETY: valid create info; the buffer is destroyed in Drop.
        let handle = unsafe { device.raw.create_buffer(&info, None) }.vk("vkCreateBuffer")?;
        // SAFETY: `handle` is a live buffer of this device.
        let requirements = unsafe { device.raw.get_buffer_memory_requirements(handle) };
        let allocation = device
            .allocator()
            .allocate(&AllocationCreateDesc {
                name,
                requirements,
                location,
                linear: true,
                allocation_scheme: AllocationScheme::GpuAllocatorManaged,
            })
            .map_err(|e| {
                // SAFETY: the buffer has no memory bound and is not in use.
                unsafe { device.raw.destroy_buffer(handle, None) };
                alloc_err(name, e)
            })?;
        // SAFETY: the allocation satisfies `requirements`; memory and offset come from it.
        unsafe { device.raw.bind_buffer_memory(handle, allocation.memory(), allocation.offset()) }
            .vk("vkBindBufferMemory")?;
        Ok(Buffer { device: device.clone(), handle, allocation: Some(allocation), size })
    }

    /// A host-visible buffer filled with `data`.
    pub fn with_data(device: &Arc<Device>, name: &str, data: &[u8], usage: vk::BufferUsageFlags) -> VkResult<Self> {
        let mut b = Buffer::new(device, name, data.len() as u64, usage, MemoryLocation::CpuToGpu)?;
        b.mapped_mut()?[..data.len()].copy_from_slice(data);
        Ok(b)
    }

    /// The mapped bytes of a host-visible buffer (lavapipe and most drivers give
    /// coherent host memory; gpu-allocator picks coherent types for these locations).
    pub fn mapped(&self) -> VkResult<&[u8]> {
        self.allocation
            .as_ref()
            .and_then(|a| a.mapped_slice())
            .ok_or_else(|| VkError::Setup("buffer is not host-visible".into()))
    }

    pub fn mapped_mut(&mut self) -> VkResult<&mut [u8]> {
        self.allocation
            .as_mut()
            .and_then(|a| a.mapped_slice_mut())
            .ok_or_else(|| VkError::Setup("buffer is not host-visible".into()))
    }
}

impl Drop for Buffer {
    fn drop(&mut self) {
        // SAFETY: owners drop GPU resources only after the work using them completed.
        unsafe { self.device.raw.destroy_buffer(self.handle, None) };
        if let Some(a) = self.allocation.take() {
            let _ = self.device.allocator().free(a);
        }
    }
}

pub struct Image {
    device: Arc<Device>,
    pub handle: vk::Image,
    allocation: Option<Allocation>,
    pub format: vk::Format,
    pub extent: vk::Extent2D,
    pub mip_levels: u32,
    /// Array layers (1 but for the heightfield atlas).
    pub layers: u32,
    /// A view of every mip level (and every layer: a 2D array view when there are layers).
    pub view: vk::ImageView,
}

impl Image {
    /// A 2D image; `shared` images are read by both activities and use CONCURRENT sharing
    /// when their queues come from different families (SPEC section 6).
    pub fn new(
        device: &Arc<Device>,
        name: &str,
        extent: vk::Extent2D,
        format: vk::Format,
        mip_levels: u32,
        usage: vk::ImageUsageFlags,
        shared: bool,
    ) -> VkResult<Self> {
        Self::with_layers(device, name, extent, format, mip_levels, 1, usage, shared, false)
    }

    /// A 2D image of `layers` array layers, viewed as a 2D array (one mip).
    pub fn array(
        device: &Arc<Device>,
        name: &str,
        extent: vk::Extent2D,
        format: vk::Format,
        layers: u32,
        usage: vk::ImageUsageFlags,
        shared: bool,
    ) -> VkResult<Self> {
        let max = device.properties.limits.max_image_array_layers;
        if layers == 0 || layers > max {
            return Err(VkError::Setup(format!("{name}: {layers} layers, the device allows 1 to {max}")));
        }
        Self::with_layers(device, name, extent, format, 1, layers, usage, shared, true)
    }

    #[allow(clippy::too_many_arguments)]
    fn with_layers(
        device: &Arc<Device>,
        name: &str,
        extent: vk::Extent2D,
        format: vk::Format,
        mip_levels: u32,
        layers: u32,
        usage: vk::ImageUsageFlags,
        shared: bool,
        array: bool,
    ) -> VkResult<Self> {
        let max = device.max_image_dimension_2d();
        if extent.width > max || extent.height > max {
            return Err(VkError::Setup(format!(
                "{name}: {} x {} is larger than the device's maxImageDimension2D ({max})",
                extent.width, extent.height
            )));
        }
        let concurrent = shared && device.families.len() > 1;
        let mut info = vk::ImageCreateInfo::default()
            .image_type(vk::ImageType::TYPE_2D)
            .format(format)
            .extent(vk::Extent3D { width: extent.width, height: extent.height, depth: 1 })
            .mip_levels(mip_levels)
            .array_layers(layers)
            .samples(vk::SampleCountFlags::TYPE_1)
            .tiling(vk::ImageTiling::OPTIMAL)
            .usage(usage)
            .initial_layout(vk::ImageLayout::UNDEFINED);
        info = if concurrent {
            info.sharing_mode(vk::SharingMode::CONCURRENT).queue_family_indices(&device.families)
        } else {
            info.sharing_mode(vk::SharingMode::EXCLUSIVE)
        };
        // SAFETY: valid create info; destroyed in Drop.
        let handle = unsafe { device.raw.create_image(&info, None) }.vk("vkCreateImage")?;
        // SAFETY: live image of this device.
        let requirements = unsafe { device.raw.get_image_memory_requirements(handle) };
        let allocation = device
            .allocator()
            .allocate(&AllocationCreateDesc {
                name,
                requirements,
                location: MemoryLocation::GpuOnly,
                linear: false,
                allocation_scheme: AllocationScheme::GpuAllocatorManaged,
            })
            .map_err(|e| {
                // SAFETY: unused image with no memory bound.
                unsafe { device.raw.destroy_image(handle, None) };
                alloc_err(name, e)
            })?;
        // SAFETY: allocation satisfies the requirements.
        unsafe { device.raw.bind_image_memory(handle, allocation.memory(), allocation.offset()) }
            .vk("vkBindImageMemory")?;
        let aspect = aspect_of(format);
        let view = create_view(device, handle, format, aspect, 0, mip_levels, if array { layers } else { 0 })?;
        Ok(Image {
            device: device.clone(),
            handle,
            allocation: Some(allocation),
            format,
            extent,
            mip_levels,
            layers,
            view,
        })
    }

    /// A view of `count` mips starting at `base`.
    pub fn mip_view(&self, base: u32, count: u32) -> VkResult<ImageView> {
        Ok(ImageView {
            device: self.device.clone(),
            handle: create_view(&self.device, self.handle, self.format, aspect_of(self.format), base, count, 0)?,
        })
    }

    pub fn range(&self, base_mip: u32, count: u32) -> vk::ImageSubresourceRange {
        vk::ImageSubresourceRange {
            aspect_mask: aspect_of(self.format),
            base_mip_level: base_mip,
            level_count: count,
            base_array_layer: 0,
            layer_count: self.layers,
        }
    }
}

fn aspect_of(format: vk::Format) -> vk::ImageAspectFlags {
    match format {
        vk::Format::D32_SFLOAT | vk::Format::D16_UNORM => vk::ImageAspectFlags::DEPTH,
        _ => vk::ImageAspectFlags::COLOR,
    }
}

/// A view of mips `base..base + count`; `layers` 0 is a 2D view, N a 2D-array view of N
/// layers.
fn create_view(
    device: &Device,
    image: vk::Image,
    format: vk::Format,
    aspect: vk::ImageAspectFlags,
    base: u32,
    count: u32,
    layers: u32,
) -> VkResult<vk::ImageView> {
    // Layered images are arrays even with one layer (the shader's sampler2DArray).
    let view_type = if layers > 0 { vk::ImageViewType::TYPE_2D_ARRAY } else { vk::ImageViewType::TYPE_2D };
    let layers = layers.max(1);
    let info = vk::ImageViewCreateInfo::default().image(image).view_type(view_type).format(format).subresource_range(
        vk::ImageSubresourceRange {
            aspect_mask: aspect,
            base_mip_level: base,
            level_count: count,
            base_array_layer: 0,
            layer_count: layers,
        },
    );
    // SAFETY: `image` is live and the range lies within it.
    unsafe { device.raw.create_image_view(&info, None) }.vk("vkCreateImageView")
}

impl Drop for Image {
    fn drop(&mut self) {
        // SAFETY: no GPU work uses the image any more (owners wait before dropping).
        unsafe {
            self.device.raw.destroy_image_view(self.view, None);
            self.device.raw.destroy_image(self.handle, None);
        }
        if let Some(a) = self.allocation.take() {
            let _ = self.device.allocator().free(a);
        }
    }
}

pub struct ImageView {
    device: Arc<Device>,
    pub handle: vk::ImageView,
}

impl Drop for ImageView {
    fn drop(&mut self) {
        // SAFETY: views are dropped with (before) their image, after the GPU is done.
        unsafe { self.device.raw.destroy_image_view(self.handle, None) };
    }
}

pub struct Sampler {
    device: Arc<Device>,
    pub handle: vk::Sampler,
}

impl Sampler {
    pub fn new(device: &Arc<Device>, filter: vk::Filter, address: vk::SamplerAddressMode) -> VkResult<Self> {
        let info = vk::SamplerCreateInfo::default()
            .mag_filter(filter)
            .min_filter(filter)
            .mipmap_mode(vk::SamplerMipmapMode::NEAREST)
            .address_mode_u(address)
            .address_mode_v(address)
            .address_mode_w(address)
            .max_lod(vk::LOD_CLAMP_NONE);
        // SAFETY: valid create info.
        let handle = unsafe { device.raw.create_sampler(&info, None) }.vk("vkCreateSampler")?;
        Ok(Sampler { device: device.clone(), handle })
    }
}

impl Drop for Sampler {
    fn drop(&mut self) {
        // SAFETY: dropped after the descriptor sets using it are no longer in use.
        unsafe { self.device.raw.destroy_sampler(self.handle, None) };
    }
}
