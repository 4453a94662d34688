//! Window surface and swapchain.

use super::device::Device;
use super::error::{VkError, VkResult, VkResultExt};
use super::instance::Instance;
use ash::vk;
use std::sync::Arc;

pub struct Surface {
    instance: Arc<Instance>,
    pub loader: ash::khr::surface::Instance,
    pub handle: vk::SurfaceKHR,
}

impl Surface {
    /// # Safety
    /// The display and window handles must stay valid until the surface is dropped.
    pub unsafe fn new(
        instance: &Arc<Instance>,
        display: raw_window_handle::RawDisplayHandle,
        window: raw_window_handle::RawWindowHandle,
    ) -> VkResult<Self> {
        // SAFETY: the caller keeps the window alive; the instance enabled the surface
        // extensions ash-window asked for.
        let handle = unsafe { ash_window::create_surface(&instance.entry, &instance.raw, display, window, None) }
            .vk("vkCreateSurfaceKHR")?;
        Ok(Surface {
            loader: ash::khr::surface::Instance::new(&instance.entry, &instance.raw),
            handle,
            instance: instance.clone(),
        })
    }
}

impl Drop for Surface {
    fn drop(&mut self) {
        // SAFETY: the swapchain built on it is destroyed first (its owner drops it first).
        unsafe { self.loader.destroy_surface(self.handle, None) };
        let _ = &self.instance;
    }
}

pub struct Swapchain {
    device: Arc<Device>,
    pub loader: ash::khr::swapchain::Device,
    pub handle: vk::SwapchainKHR,
    pub images: Vec<vk::Image>,
    pub views: Vec<vk::ImageView>,
    pub format: vk::Format,
    pub extent: vk::Extent2D,
    /// Signalled when rendering to image i is done; one per image, because a present
    /// may still be waiting on it when the same frame slot comes round again.
    pub render_done: Vec<vk::Semaphore>,
    /// The images can be copied from (for screenshots).
    pub can_copy: bool,
}

impl Swapchain {
    pub fn new(
        device: &Arc<Device>,
        surface: &Surface,
        size: (u32, u32),
        present_mode: vk::PresentModeKHR,
        old: Option<&Swapchain>,
    ) -> VkResult<Self> {
        let pd = device.physical;
        // SAFETY: queries on live objects.
        let (caps, formats, modes, supported) = unsafe {
            (
                surface
                    .loader
                    .get_physical_device_surface_capabilities(pd, surface.handle)
                    .vk("vkGetPhysicalDeviceSurfaceCapabilitiesKHR")?,
                surface
                    .loader
                    .get_physical_device_surface_formats(pd, surface.handle)
                    .vk("vkGetPhysicalDeviceSurfaceFormatsKHR")?,
                surface
                    .loader
                    .get_physical_device_surface_present_modes(pd, surface.handle)
                    .vk("vkGetPhysicalDeviceSurfacePresentModesKHR")?,
                surface
                    .loader
                    .get_physical_device_surface_support(pd, device.draw_queue.family, surface.handle)
                    .vk("vkGetPhysicalDeviceSurfaceSupportKHR")?,
            )
        };
        if !supported {
            return Err(VkError::Setup(format!("{}: the draw queue cannot present to this window", device.name)));
        }
        let format = formats
            .iter()
            .find(|f| {
                matches!(f.format, vk::Format::B8G8R8A8_SRGB | vk::Format::R8G8B8A8_SRGB)
                    && f.color_space == vk::ColorSpaceKHR::SRGB_NONLINEAR
            })
            .or(formats.first())
            .copied()
            .ok_or_else(|| VkError::Setup("the surface offers no formats".into()))?;
        let mode = if modes.contains(&present_mode) {
            present_mode
        } else {
            tracing::warn!("present mode {present_mode:?} not supported; using FIFO");
            vk::PresentModeKHR::FIFO
        };
        let extent = if caps.current_extent.width != u32::MAX {
            caps.current_extent
        } else {
            vk::Extent2D {
                width: size.0.clamp(caps.min_image_extent.width, caps.max_image_extent.width),
                height: size.1.clamp(caps.min_image_extent.height, caps.max_image_extent.height),
            }
        };
        let mut count = caps.min_image_count + 1;
        if caps.max_image_count > 0 {
            count = count.min(caps.max_image_count);
        }
        let can_copy = caps.supported_usage_flags.contains(vk::ImageUsageFlags::TRANSFER_SRC);
        let mut usage = vk::ImageUsageFlags::COLOR_ATTACHMENT;
        if can_copy {
            usage |= vk::ImageUsageFlags::TRANSFER_SRC;
        }
        let info = vk::SwapchainCreateInfoKHR::default()
            .surface(surface.handle)
            .min_image_count(count)
            .image_format(format.format)
            .image_color_space(format.color_space)
            .image_extent(extent)
            .image_array_layers(1)
            .image_usage(usage)
            .image_sharing_mode(vk::SharingMode::EXCLUSIVE)
            .pre_transform(caps.current_transform)
            .composite_alpha(vk::CompositeAlphaFlagsKHR::OPAQUE)
            .present_mode(mode)
            .clipped(true)
            .old_swapchain(old.map_or(vk::SwapchainKHR::null(), |o| o.handle));
        let loader = ash::khr::swapchain::Device::new(&device.instance.raw, &device.raw);
        // SAFETY: valid create info; the old swapchain is retired by this call.
        let handle = unsafe { loader.create_swapchain(&info, None) }.vk("vkCreateSwapchainKHR")?;
        // SAFETY: live swapchain.
        let images = unsafe { loader.get_swapchain_images(handle) }.vk("vkGetSwapchainImagesKHR")?;
        let mut views = Vec::new();
        let mut render_done = Vec::new();
        for &image in &images {
            let vi = vk::ImageViewCreateInfo::default()
                .image(image)
                .view_type(vk::ImageViewType::TYPE_2D)
                .format(format.format)
                .subresource_range(vk::ImageSubresourceRange {
                    aspect_mask: vk::ImageAspectFlags::COLOR,
                    base_mip_level: 0,
                    level_count: 1,
                    base_array_layer: 0,
                    layer_count: 1,
                });
            // SAFETY: `image` belongs to the swapchain.
            views.push(unsafe { device.raw.create_image_view(&vi, None) }.vk("vkCreateImageView")?);
            // SAFETY: plain binary semaphore.
            render_done.push(
                unsafe { device.raw.create_semaphore(&vk::SemaphoreCreateInfo::default(), None) }
                    .vk("vkCreateSemaphore")?,
            );
        }
        Ok(Swapchain {
            device: device.clone(),
            loader,
            handle,
            images,
            views,
            format: format.format,
            extent,
            render_done,
            can_copy,
        })
    }
}

impl Drop for Swapchain {
    fn drop(&mut self) {
        // SAFETY: the owner waits for the device to be idle before dropping a swapchain.
        unsafe {
            for &v in &self.views {
                self.device.raw.destroy_image_view(v, None);
            }
            for &s in &self.render_done {
                self.device.raw.destroy_semaphore(s, None);
            }
            self.loader.destroy_swapchain(self.handle, None);
        }
    }
}
