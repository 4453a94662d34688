//! A thin layer of owning types over ash. Every Vulkan object lives in a Rust value that
//! destroys it in `Drop`; children hold an `Arc<Device>`, so the device (and then the
//! instance) outlives everything created from it.

mod command;
mod device;
mod instance;
mod pipeline;
mod resources;
mod swapchain;

pub use command::{
    begin_one_time, image_barrier, BinarySemaphore, CommandPool, Fence, ImageUse, QueryPool, TimelineSemaphore,
};
pub use device::{Device, DeviceOptions, Queue, QueueMode, QueueRequest};
pub use instance::{Instance, InstanceOptions, MessageCounter};
pub use pipeline::{
    DepthMode, DescriptorPool, DescriptorSetLayout, GraphicsPipeline, GraphicsPipelineDesc, PipelineLayout,
};
pub use resources::{Buffer, Image, ImageView, Sampler};
pub use swapchain::{Surface, Swapchain};

pub use ash::vk;
use std::backtrace::Backtrace;

/// A failed Vulkan call or allocation, with where it happened.
#[derive(Debug, thiserror::Error)]
pub enum VkError {
    #[error("{call} failed: {result:?}")]
    Call {
        call: &'static str,
        result: vk::Result,
        /// Captured when RUST_BACKTRACE is set (a String: stable thiserror cannot
        /// forward a `Backtrace` field).
        trace: String,
    },
    #[error("GPU memory allocation for {what} failed: {message}")]
    Alloc { what: String, message: String },
    #[error("{0}")]
    Setup(String),
}

impl VkError {
    /// True when the device was lost (the caller names the stage and stops).
    pub fn is_device_lost(&self) -> bool {
        matches!(self, VkError::Call { result: vk::Result::ERROR_DEVICE_LOST, .. })
    }
}

pub type VkResult<T> = Result<T, VkError>;

/// `.vk("vkCall")?` turns an ash result into a [`VkError`] naming the call.
pub trait VkResultExt<T> {
    fn vk(self, call: &'static str) -> VkResult<T>;
}

impl<T> VkResultExt<T> for Result<T, vk::Result> {
    fn vk(self, call: &'static str) -> VkResult<T> {
        self.map_err(|result| VkError::Call { call, result, trace: Backtrace::capture().to_string() })
    }
}
