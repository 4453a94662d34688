//! Command pools (one per thread), fences and timeline semaphores.

use super::device::Device;
use super::error::{VkResult, VkResultExt};
use super::resources::Buffer;
use ash::vk;
use std::sync::Arc;

/// A command pool; owned by one thread (command pools are externally synchronized).
pub struct CommandPool {
    device: Arc<Device>,
    pub handle: vk::CommandPool,
}

impl CommandPool {
    pub fn new(device: &Arc<Device>, family: u32) -> VkResult<Self> {
        let info = vk::CommandPoolCreateInfo::default()
            .queue_family_index(family)
            .flags(vk::CommandPoolCreateFlags::RESET_COMMAND_BUFFER);
        // SAFETY: valid create info.
        let handle = unsafe { device.raw.create_command_pool(&info, None) }.vk("vkCreateCommandPool")?;
        Ok(CommandPool { device: device.clone(), handle })
    }

    pub fn allocate(&self) -> VkResult<vk::CommandBuffer> {
        let info = vk::CommandBufferAllocateInfo::default()
            .command_pool(self.handle)
            .level(vk::CommandBufferLevel::PRIMARY)
            .command_buffer_count(1);
        // SAFETY: the pool is live and used by this thread only.
        Ok(unsafe { self.device.raw.allocate_command_buffers(&info) }.vk("vkAllocateCommandBuffers")?[0])
    }

    pub fn free(&self, cmd: vk::CommandBuffer) {
        // SAFETY: callers free a command buffer only after its submission completed.
        unsafe { self.device.raw.free_command_buffers(self.handle, &[cmd]) };
    }
}

impl Drop for CommandPool {
    fn drop(&mut self) {
        // SAFETY: the owner has waited for its submissions; destroying the pool frees its
        // command buffers.
        unsafe { self.device.raw.destroy_command_pool(self.handle, None) };
    }
}

// The device's one-shot submission lives beside the pool and fence it uses, so that
// device.rs needs nothing from this file.
impl Device {
    /// Records commands into a one-time command buffer, submits them on the draw queue
    /// and waits (used for uploads before the activities start).
    pub fn one_shot(self: &Arc<Self>, pool: &CommandPool, record: impl FnOnce(vk::CommandBuffer)) -> VkResult<()> {
        let cmd = pool.allocate()?;
        let begin = vk::CommandBufferBeginInfo::default().flags(vk::CommandBufferUsageFlags::ONE_TIME_SUBMIT);
        // SAFETY: `cmd` was just allocated from `pool`, which this thread owns.
        unsafe { self.raw.begin_command_buffer(cmd, &begin) }.vk("vkBeginCommandBuffer")?;
        record(cmd);
        // SAFETY: as above.
        unsafe { self.raw.end_command_buffer(cmd) }.vk("vkEndCommandBuffer")?;
        let fence = Fence::new(self, false)?;
        let cmds = [vk::CommandBufferSubmitInfo::default().command_buffer(cmd)];
        let submit = [vk::SubmitInfo2::default().command_buffer_infos(&cmds)];
        self.draw_queue.submit(self, &submit, fence.handle)?;
        fence.wait(u64::MAX)?;
        pool.free(cmd);
        Ok(())
    }
}

pub struct Fence {
    device: Arc<Device>,
    pub handle: vk::Fence,
}

impl Fence {
    pub fn new(device: &Arc<Device>, signaled: bool) -> VkResult<Self> {
        let flags = if signaled { vk::FenceCreateFlags::SIGNALED } else { vk::FenceCreateFlags::empty() };
        // SAFETY: valid create info.
        let handle = unsafe { device.raw.create_fence(&vk::FenceCreateInfo::default().flags(flags), None) }
            .vk("vkCreateFence")?;
        Ok(Fence { device: device.clone(), handle })
    }

    pub fn wait(&self, timeout_ns: u64) -> VkResult<()> {
        // SAFETY: live fence.
        unsafe { self.device.raw.wait_for_fences(&[self.handle], true, timeout_ns) }.vk("vkWaitForFences")
    }

    pub fn reset(&self) -> VkResult<()> {
        // SAFETY: the fence is not in use by a pending submission (waited first).
        unsafe { self.device.raw.reset_fences(&[self.handle]) }.vk("vkResetFences")
    }
}

impl Drop for Fence {
    fn drop(&mut self) {
        // SAFETY: callers wait on the fence before dropping it.
        unsafe { self.device.raw.destroy_fence(self.handle, None) };
    }
}

/// A timeline semaphore: its value is a generation counter.
pub struct TimelineSemaphore {
    device: Arc<Device>,
    pub handle: vk::Semaphore,
}

impl TimelineSemaphore {
    pub fn new(device: &Arc<Device>, initial: u64) -> VkResult<Self> {
        let mut t =
            vk::SemaphoreTypeCreateInfo::default().semaphore_type(vk::SemaphoreType::TIMELINE).initial_value(initial);
        let info = vk::SemaphoreCreateInfo::default().push_next(&mut t);
        // SAFETY: valid create info.
        let handle = unsafe { device.raw.create_semaphore(&info, None) }.vk("vkCreateSemaphore")?;
        Ok(TimelineSemaphore { device: device.clone(), handle })
    }

    /// The current value, read on the CPU (never a GPU wait).
    pub fn value(&self) -> VkResult<u64> {
        // SAFETY: live timeline semaphore.
        unsafe { self.device.raw.get_semaphore_counter_value(self.handle) }.vk("vkGetSemaphoreCounterValue")
    }

    /// Waits on the CPU until the value reaches `value`; false on timeout.
    pub fn wait(&self, value: u64, timeout_ns: u64) -> VkResult<bool> {
        let sems = [self.handle];
        let values = [value];
        let info = vk::SemaphoreWaitInfo::default().semaphores(&sems).values(&values);
        // SAFETY: live semaphore; arrays outlive the call.
        match unsafe { self.device.raw.wait_semaphores(&info, timeout_ns) } {
            Ok(()) => Ok(true),
            Err(vk::Result::TIMEOUT) => Ok(false),
            Err(e) => Err(e).vk("vkWaitSemaphores"),
        }
    }
}

impl Drop for TimelineSemaphore {
    fn drop(&mut self) {
        // SAFETY: owners wait for the last signal before dropping.
        unsafe { self.device.raw.destroy_semaphore(self.handle, None) };
    }
}

/// Resets `cmd` and begins recording it for one submission.
///
/// # Safety
/// `cmd` must belong to a pool with RESET_COMMAND_BUFFER, be used by this thread only,
/// and its previous submission must have completed.
pub unsafe fn begin_one_time(d: &ash::Device, cmd: vk::CommandBuffer) -> VkResult<()> {
    // SAFETY: guaranteed by the caller (see above).
    unsafe {
        d.reset_command_buffer(cmd, vk::CommandBufferResetFlags::empty()).vk("vkResetCommandBuffer")?;
        let begin = vk::CommandBufferBeginInfo::default().flags(vk::CommandBufferUsageFlags::ONE_TIME_SUBMIT);
        d.begin_command_buffer(cmd, &begin).vk("vkBeginCommandBuffer")
    }
}

/// Where an image was last used, or will be used next: stage, access and layout.
pub type ImageUse = (vk::PipelineStageFlags2, vk::AccessFlags2, vk::ImageLayout);

/// Read by fragment shaders through a sampler.
pub const FRAGMENT_SAMPLED: ImageUse = (
    vk::PipelineStageFlags2::FRAGMENT_SHADER,
    vk::AccessFlags2::SHADER_SAMPLED_READ,
    vk::ImageLayout::SHADER_READ_ONLY_OPTIMAL,
);

/// The source of a copy.
pub const COPY_SOURCE: ImageUse =
    (vk::PipelineStageFlags2::COPY, vk::AccessFlags2::TRANSFER_READ, vk::ImageLayout::TRANSFER_SRC_OPTIMAL);

/// Records one image barrier from `from` to `to` over `range`.
///
/// # Safety
/// `cmd` must be a command buffer of `d` in the recording state, used by this thread only,
/// and `image` must stay alive until its submission completes.
pub unsafe fn image_barrier(
    d: &ash::Device,
    cmd: vk::CommandBuffer,
    image: vk::Image,
    range: vk::ImageSubresourceRange,
    from: ImageUse,
    to: ImageUse,
) {
    let b = [vk::ImageMemoryBarrier2::default()
        .src_stage_mask(from.0)
        .src_access_mask(from.1)
        .old_layout(from.2)
        .dst_stage_mask(to.0)
        .dst_access_mask(to.1)
        .new_layout(to.2)
        .image(image)
        .subresource_range(range)];
    // SAFETY: guaranteed by the caller (see above).
    unsafe { d.cmd_pipeline_barrier2(cmd, &vk::DependencyInfo::default().image_memory_barriers(&b)) };
}

/// A binary semaphore (swapchain acquire).
pub struct BinarySemaphore {
    device: Arc<Device>,
    pub handle: vk::Semaphore,
}

impl BinarySemaphore {
    pub fn new(device: &Arc<Device>) -> VkResult<Self> {
        // SAFETY: valid create info.
        let handle = unsafe { device.raw.create_semaphore(&vk::SemaphoreCreateInfo::default(), None) }
            .vk("vkCreateSemaphore")?;
        Ok(BinarySemaphore { device: device.clone(), handle })
    }
}

impl Drop for BinarySemaphore {
    fn drop(&mut self) {
        // SAFETY: the owner waits for the device to be idle first.
        unsafe { self.device.raw.destroy_semaphore(self.handle, None) };
    }
}

/// Where GPU timestamps fall on the CPU clock (see `QueryPool::calibrate`).
#[derive(Clone, Copy, Debug)]
pub struct GpuClock {
    pub tick_at: u64,
    pub cpu_at: std::time::Instant,
    pub period_ns: f64,
    /// How far off the placement may be, microseconds.
    pub uncertainty_us: f64,
    /// How the clocks were related (written into the trace's metadata).
    pub method: &'static str,
}

/// A timestamp query pool (optional: only on queues with timestamp bits).
pub struct QueryPool {
    device: Arc<Device>,
    pub handle: vk::QueryPool,
    /// Nanoseconds per tick.
    pub period_ns: f64,
}

impl QueryPool {
    /// `None` when the queue family has no timestamps.
    pub fn timestamps(device: &Arc<Device>, count: u32) -> VkResult<Option<Self>> {
        let Some(period) = device.features.timestamp_period else { return Ok(None) };
        let info = vk::QueryPoolCreateInfo::default().query_type(vk::QueryType::TIMESTAMP).query_count(count);
        // SAFETY: valid create info.
        let handle = unsafe { device.raw.create_query_pool(&info, None) }.vk("vkCreateQueryPool")?;
        Ok(Some(QueryPool { device: device.clone(), handle, period_ns: period as f64 }))
    }

    /// Records a copy of `count` timestamps from `first` into `buffer` at `offset` (u64
    /// each, waiting on the GPU for them), then makes them visible to the host. Reading
    /// them from the buffer after the submission's fence needs no Vulkan call: on some
    /// drivers (lavapipe) vkGetQueryPoolResults waits for the whole queue to go idle,
    /// which defeats frames in flight.
    ///
    /// # Safety
    /// `cmd` is recording; `buffer` holds `offset + 8 * count` bytes and outlives the
    /// submission; the queries are written earlier in submission order.
    pub unsafe fn record_copy(&self, cmd: vk::CommandBuffer, first: u32, count: u32, buffer: vk::Buffer, offset: u64) {
        // SAFETY: guaranteed by the caller (see above).
        unsafe { record_query_copy(&self.device.raw, cmd, self.handle, first, count, buffer, offset) }
    }

    /// Milliseconds between two ticks.
    pub fn ms(&self, ticks: [u64; 2]) -> f64 {
        ticks[1].wrapping_sub(ticks[0]) as f64 * self.period_ns / 1e6
    }

    /// Places GPU timestamps on the CPU clock: one timestamp written by a submission on
    /// the draw queue, taken at the midpoint of the CPU's submit-to-fence window (the
    /// device may lack VK_EXT_calibrated_timestamps; this works everywhere, to within
    /// that window).
    pub fn calibrate(device: &Arc<Device>) -> VkResult<Option<GpuClock>> {
        let Some(pool) = QueryPool::timestamps(device, 1)? else { return Ok(None) };
        if let Some(ext) = &device.calibrated_timestamps {
            // The device and CLOCK_MONOTONIC (Rust's Instant on Linux) sampled together;
            // the CPU side is placed at the midpoint of the call, which takes microseconds.
            let infos = [
                vk::CalibratedTimestampInfoEXT::default().time_domain(vk::TimeDomainEXT::DEVICE),
                vk::CalibratedTimestampInfoEXT::default().time_domain(vk::TimeDomainEXT::CLOCK_MONOTONIC),
            ];
            let before = std::time::Instant::now();
            // SAFETY: the extension is enabled on this device; `infos` is valid.
            let (stamps, deviation_ns) =
                unsafe { ext.get_calibrated_timestamps(&infos) }.vk("vkGetCalibratedTimestampsEXT")?;
            let after = std::time::Instant::now();
            return Ok(Some(GpuClock {
                tick_at: stamps[0],
                cpu_at: before + (after - before) / 2,
                period_ns: pool.period_ns,
                uncertainty_us: (after - before).as_secs_f64() * 1e6 / 2.0 + deviation_ns as f64 / 1e3,
                method: "VK_EXT_calibrated_timestamps (device and CLOCK_MONOTONIC sampled together)",
            }));
        }
        let commands = CommandPool::new(device, device.draw_queue.family)?;
        let before = std::time::Instant::now();
        device.one_shot(&commands, |cmd| {
            // SAFETY: recording; the pool is ours and outlives the wait in one_shot.
            unsafe {
                device.raw.cmd_reset_query_pool(cmd, pool.handle, 0, 1);
                device.raw.cmd_write_timestamp2(cmd, vk::PipelineStageFlags2::TOP_OF_PIPE, pool.handle, 0);
            }
        })?;
        let after = std::time::Instant::now();
        let mut tick = [0u64; 1];
        // SAFETY: the submission completed (one_shot waited).
        unsafe { device.raw.get_query_pool_results(pool.handle, 0, &mut tick, vk::QueryResultFlags::TYPE_64) }
            .vk("vkGetQueryPoolResults")?;
        Ok(Some(GpuClock {
            tick_at: tick[0],
            cpu_at: before + (after - before) / 2,
            period_ns: pool.period_ns,
            uncertainty_us: (after - before).as_secs_f64() * 1e6 / 2.0,
            method: "measured offset: one timestamp at the midpoint of its submit-to-fence window",
        }))
    }
}

impl Drop for QueryPool {
    fn drop(&mut self) {
        // SAFETY: the owner waits for the GPU before dropping.
        unsafe { self.device.raw.destroy_query_pool(self.handle, None) };
    }
}

/// [`QueryPool::record_copy`] for a pool known by its handle.
///
/// # Safety
/// As for [`QueryPool::record_copy`]; `pool` belongs to `d`.
pub unsafe fn record_query_copy(
    d: &ash::Device,
    cmd: vk::CommandBuffer,
    pool: vk::QueryPool,
    first: u32,
    count: u32,
    buffer: vk::Buffer,
    offset: u64,
) {
    let flags = vk::QueryResultFlags::TYPE_64 | vk::QueryResultFlags::WAIT;
    // SAFETY: guaranteed by the caller (see above).
    unsafe {
        d.cmd_copy_query_pool_results(cmd, pool, first, count, buffer, offset, 8, flags);
        host_read_barrier(d, cmd, buffer, (vk::PipelineStageFlags2::COPY, vk::AccessFlags2::TRANSFER_WRITE));
    }
}

/// Makes the writes to `buffer` of `written` (stage and access) visible to the host
/// after the submission's fence or semaphore.
///
/// # Safety
/// `cmd` is recording and `buffer` outlives its submission.
pub unsafe fn host_read_barrier(
    d: &ash::Device,
    cmd: vk::CommandBuffer,
    buffer: vk::Buffer,
    written: (vk::PipelineStageFlags2, vk::AccessFlags2),
) {
    let to_host = [vk::BufferMemoryBarrier2::default()
        .src_stage_mask(written.0)
        .src_access_mask(written.1)
        .dst_stage_mask(vk::PipelineStageFlags2::HOST)
        .dst_access_mask(vk::AccessFlags2::HOST_READ)
        .buffer(buffer)
        .size(vk::WHOLE_SIZE)];
    // SAFETY: guaranteed by the caller (see above).
    unsafe { d.cmd_pipeline_barrier2(cmd, &vk::DependencyInfo::default().buffer_memory_barriers(&to_host)) };
}

/// The begin and end timestamps of one frame's commands, copied to a host buffer on the
/// GPU (see [`QueryPool::record_copy`]). `None` from [`FrameTimer::new`] when the queue
/// has no timestamps.
pub struct FrameTimer {
    pool: QueryPool,
    buffer: Buffer,
}

impl FrameTimer {
    pub fn new(device: &Arc<Device>) -> VkResult<Option<Self>> {
        let Some(pool) = QueryPool::timestamps(device, 2)? else { return Ok(None) };
        let buffer = Buffer::new(
            device,
            "frame timestamps",
            16,
            vk::BufferUsageFlags::TRANSFER_DST,
            gpu_allocator::MemoryLocation::GpuToCpu,
        )?;
        Ok(Some(FrameTimer { pool, buffer }))
    }

    /// Records the start timestamp (first in the command buffer).
    ///
    /// # Safety
    /// `cmd` is recording; this timer's previous frame has completed.
    pub unsafe fn begin(&self, d: &ash::Device, cmd: vk::CommandBuffer) {
        // SAFETY: guaranteed by the caller (see above).
        unsafe {
            d.cmd_reset_query_pool(cmd, self.pool.handle, 0, 2);
            d.cmd_write_timestamp2(cmd, vk::PipelineStageFlags2::TOP_OF_PIPE, self.pool.handle, 0);
        }
    }

    /// Records the end timestamp and the copy to the host buffer (last in the buffer).
    ///
    /// # Safety
    /// As for [`FrameTimer::begin`], in the same command buffer after it.
    pub unsafe fn end(&self, d: &ash::Device, cmd: vk::CommandBuffer) {
        // SAFETY: guaranteed by the caller (see above).
        unsafe {
            d.cmd_write_timestamp2(cmd, vk::PipelineStageFlags2::BOTTOM_OF_PIPE, self.pool.handle, 1);
            self.pool.record_copy(cmd, 0, 2, self.buffer.handle, 0);
        }
    }

    /// The frame's ticks and milliseconds; only after its submission completed.
    pub fn read(&self) -> VkResult<([u64; 2], f64)> {
        let t: Vec<u64> = bytemuck::pod_collect_to_vec(&self.buffer.mapped()?[..16]);
        let ticks = [t[0], t[1]];
        Ok((ticks, self.pool.ms(ticks)))
    }
}

/// Records a copy of a colour image's first `extent` texels (from its top left corner;
/// the whole image when `extent` is its size; in TRANSFER_SRC_OPTIMAL) into `buffer`,
/// then a barrier that makes the bytes visible to the host after the submission's fence.
///
/// # Safety
/// `cmd` is recording and the image is in TRANSFER_SRC_OPTIMAL; `buffer` must hold `extent` texels of the image's format.
pub unsafe fn copy_image_to_host(
    d: &ash::Device,
    cmd: vk::CommandBuffer,
    image: vk::Image,
    extent: vk::Extent2D,
    buffer: vk::Buffer,
) {
    let region = vk::BufferImageCopy::default()
        .image_subresource(vk::ImageSubresourceLayers {
            aspect_mask: vk::ImageAspectFlags::COLOR,
            mip_level: 0,
            base_array_layer: 0,
            layer_count: 1,
        })
        .image_extent(vk::Extent3D { width: extent.width, height: extent.height, depth: 1 });
    // SAFETY: guaranteed by the caller (see above).
    unsafe {
        d.cmd_copy_image_to_buffer(cmd, image, vk::ImageLayout::TRANSFER_SRC_OPTIMAL, buffer, &[region]);
        host_read_barrier(d, cmd, buffer, (vk::PipelineStageFlags2::COPY, vk::AccessFlags2::TRANSFER_WRITE));
    }
}
