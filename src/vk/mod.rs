//! A thin layer of owning types over ash. Every Vulkan object lives in a Rust value that
//! destroys it in `Drop`; children hold an `Arc<Device>`, so the device (and then the
//! instance) outlives everything created from it.

mod command;
mod device;
mod error;
mod instance;
mod pipeline;
mod resources;
mod swapchain;

pub use command::{
    begin_one_time, copy_image_to_host, host_read_barrier, image_barrier, record_query_copy, BinarySemaphore,
    CommandPool, Fence, FrameTimer, GpuClock, ImageUse, QueryPool, TimelineSemaphore, COPY_SOURCE, FRAGMENT_SAMPLED,
};
pub use device::{Device, DeviceOptions, Queue, QueueMode, QueueRequest};
pub use instance::{Instance, InstanceOptions, MessageCounter};
pub use pipeline::{
    DepthMode, DescriptorPool, DescriptorSetLayout, GraphicsPipeline, GraphicsPipelineDesc, PipelineLayout,
};
pub use resources::{Buffer, Image, ImageView, Sampler};
pub use swapchain::{Surface, Swapchain};

pub use ash::vk;
pub use error::{VkError, VkResult, VkResultExt};
