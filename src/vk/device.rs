//! Physical device selection, the logical device, its queues (SPEC section 6) and the
//! memory allocator.

use super::error::{VkError, VkResult, VkResultExt};
use super::instance::{c_name, Instance};
use ash::vk;
use gpu_allocator::vulkan::{Allocator, AllocatorCreateDesc};
use std::mem::ManuallyDrop;
use std::sync::{Arc, Mutex, MutexGuard};

/// How the two activities get their queues.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Default, clap::ValueEnum)]
pub enum QueueRequest {
    /// Two graphics queues when the device has them, else one shared queue.
    #[default]
    Auto,
    /// One queue for both activities, behind a mutex.
    Shared,
    /// Two queues, or an error if the device has only one.
    Separate,
}

/// The queue arrangement in use; printed at start-up and in every stats output.
#[derive(Clone, Copy, Debug, PartialEq, Eq, serde::Serialize)]
#[serde(rename_all = "kebab-case")]
pub enum QueueMode {
    /// Both activities submit to one queue, serialized by a mutex.
    Shared,
    /// Two queues of one family.
    SeparateSameFamily,
    /// Two queues of different families; shared images use CONCURRENT sharing.
    SeparateFamilies,
}

impl QueueMode {
    pub fn as_str(self) -> &'static str {
        match self {
            QueueMode::Shared => "shared",
            QueueMode::SeparateSameFamily => "separate-same-family",
            QueueMode::SeparateFamilies => "separate-families",
        }
    }
}

/// A queue; submission is externally synchronized through `lock`, which is the same
/// mutex for both activities when they share one queue.
#[derive(Clone)]
pub struct Queue {
    pub handle: vk::Queue,
    pub family: u32,
    lock: Arc<Mutex<()>>,
}

impl Queue {
    /// Submits under the queue's lock (vkQueueSubmit2 needs external synchronization).
    pub fn submit(&self, device: &Device, submits: &[vk::SubmitInfo2<'_>], fence: vk::Fence) -> VkResult<()> {
        self.submit_timed(device, submits, fence).map(|_| ())
    }

    /// Like [`Queue::submit`]; returns when this thread started waiting for the queue's
    /// lock and when it got it (on a shared queue, the other activity may hold it).
    pub fn submit_timed(
        &self,
        device: &Device,
        submits: &[vk::SubmitInfo2<'_>],
        fence: vk::Fence,
    ) -> VkResult<(std::time::Instant, std::time::Instant)> {
        let asked = std::time::Instant::now();
        let _guard = self.lock.lock().unwrap_or_else(|e| e.into_inner());
        let got = std::time::Instant::now();
        // SAFETY: the queue belongs to `device`; access is serialized by the lock.
        unsafe { device.raw.queue_submit2(self.handle, submits, fence) }.vk("vkQueueSubmit2")?;
        Ok((asked, got))
    }

    /// Locks the queue for calls like vkQueuePresentKHR.
    pub fn lock(&self) -> MutexGuard<'_, ()> {
        self.lock.lock().unwrap_or_else(|e| e.into_inner())
    }
}

#[derive(Clone, Debug, Default)]
pub struct DeviceOptions {
    /// Device name substring or index (`--gpu`).
    pub gpu: Option<String>,
    pub queues: QueueRequest,
    /// Needed for a window.
    pub swapchain: bool,
}

/// Optional features found on the device.
#[derive(Clone, Copy, Debug, Default)]
pub struct DeviceFeatures {
    pub wireframe: bool,
    /// Vertex shaders may write storage buffers (used by the vertex-capture test hook).
    pub vertex_stores: bool,
    pub pipeline_statistics: bool,
    /// gl_ClipDistance: deferred shading's depth pass clips the embedding margin with it
    /// (no fragment shader); without it frames are shaded forward.
    pub clip_distance: bool,
    /// Nanoseconds per timestamp tick, when the draw queue has timestamps.
    pub timestamp_period: Option<f32>,
}

pub struct Device {
    pub instance: Arc<Instance>,
    pub physical: vk::PhysicalDevice,
    pub raw: ash::Device,
    pub name: String,
    pub properties: vk::PhysicalDeviceProperties,
    pub features: DeviceFeatures,
    pub draw_queue: Queue,
    pub errors_queue: Queue,
    pub queue_mode: QueueMode,
    /// Families that use images shared by both activities (for CONCURRENT sharing).
    pub families: Vec<u32>,
    /// VK_EXT_calibrated_timestamps, when the device has it with the device and
    /// CLOCK_MONOTONIC time domains (for placing GPU work on the CPU clock).
    pub calibrated_timestamps: Option<ash::ext::calibrated_timestamps::Device>,
    /// Shared (an `Arc`) with the viewer's egui renderer, which holds an `Arc<Device>`
    /// beside its clone, so the clone is gone before this is dropped.
    allocator: ManuallyDrop<Arc<Mutex<Allocator>>>,
}

/// Chooses the queue arrangement (SPEC section 6) from each family's flags and queue
/// count: (mode, draw family, errors family).
pub fn plan_queues(families: &[(vk::QueueFlags, u32)], request: QueueRequest) -> Result<(QueueMode, u32, u32), String> {
    let graphics: Vec<u32> =
        (0..families.len() as u32).filter(|&i| families[i as usize].0.contains(vk::QueueFlags::GRAPHICS)).collect();
    let first = *graphics.first().ok_or("no graphics queue")?;
    let two_in_one = graphics.iter().copied().find(|&f| families[f as usize].1 >= 2);
    Ok(match request {
        QueueRequest::Shared => (QueueMode::Shared, first, first),
        _ => match (two_in_one, graphics.get(1)) {
            (Some(f), _) => (QueueMode::SeparateSameFamily, f, f),
            (None, Some(&second)) => (QueueMode::SeparateFamilies, first, second),
            (None, None) if request == QueueRequest::Separate => {
                return Err(
                    "--queues separate: the device has only one graphics queue; use --queues auto or shared".into()
                )
            }
            (None, None) => (QueueMode::Shared, first, first),
        },
    })
}

fn device_type_rank(t: vk::PhysicalDeviceType) -> u32 {
    match t {
        vk::PhysicalDeviceType::DISCRETE_GPU => 0,
        vk::PhysicalDeviceType::INTEGRATED_GPU => 1,
        vk::PhysicalDeviceType::VIRTUAL_GPU => 2,
        vk::PhysicalDeviceType::CPU => 3,
        _ => 4,
    }
}

impl Device {
    pub fn new(instance: Arc<Instance>, opts: &DeviceOptions) -> VkResult<Arc<Self>> {
        let inst = &instance.raw;
        // SAFETY: enumeration and property queries on a live instance.
        let physicals = unsafe { inst.enumerate_physical_devices() }.vk("vkEnumeratePhysicalDevices")?;
        if physicals.is_empty() {
            return Err(VkError::Setup(
                "no Vulkan device found; install a driver (mesa-vulkan-drivers provides lavapipe)".into(),
            ));
        }
        let described: Vec<(vk::PhysicalDevice, vk::PhysicalDeviceProperties)> = physicals
            .iter()
            // SAFETY: `p` comes from this instance.
            .map(|&p| (p, unsafe { inst.get_physical_device_properties(p) }))
            .collect();
        let names: Vec<String> = described.iter().map(|(_, pr)| c_name(&pr.device_name)).collect();
        let chosen = match &opts.gpu {
            Some(sel) => {
                // A number is an index only (device names contain digits); a name must
                // not be empty.
                let idx = match sel.trim().parse::<usize>() {
                    Ok(i) => (i < described.len()).then_some(i),
                    Err(_) if sel.trim().is_empty() => None,
                    Err(_) => names.iter().position(|n| n.to_lowercase().contains(&sel.trim().to_lowercase())),
                };
                idx.ok_or_else(|| {
                    VkError::Option(format!("--gpu {sel}: no such device; available: {}", names.join(", ")))
                })?
            }
            None => (0..described.len())
                .filter(|&i| described[i].1.api_version >= vk::API_VERSION_1_3)
                .min_by_key(|&i| device_type_rank(described[i].1.device_type))
                .ok_or_else(|| VkError::Setup(format!("no Vulkan 1.3 device among: {}", names.join(", "))))?,
        };
        let (physical, properties) = described[chosen];
        let name = names[chosen].clone();
        if properties.api_version < vk::API_VERSION_1_3 {
            return Err(VkError::Setup(format!("{name} does not support Vulkan 1.3")));
        }

        // SAFETY: query on a live physical device.
        let families = unsafe { inst.get_physical_device_queue_family_properties(physical) };
        let flags_counts: Vec<(vk::QueueFlags, u32)> =
            families.iter().map(|f| (f.queue_flags, f.queue_count)).collect();
        let mode_plan =
            plan_queues(&flags_counts, opts.queues).map_err(|e| VkError::Option(e.replace("the device", &name)))?;
        let (queue_mode, draw_family, errors_family) = mode_plan;
        let priorities = [1.0f32, 1.0];
        let mut queue_infos =
            vec![vk::DeviceQueueCreateInfo::default().queue_family_index(draw_family).queue_priorities(
                if queue_mode == QueueMode::SeparateSameFamily { &priorities[..2] } else { &priorities[..1] },
            )];
        if queue_mode == QueueMode::SeparateFamilies {
            queue_infos.push(
                vk::DeviceQueueCreateInfo::default()
                    .queue_family_index(errors_family)
                    .queue_priorities(&priorities[..1]),
            );
        }

        // SAFETY: feature query on a live physical device.
        let supported = unsafe { inst.get_physical_device_features(physical) };
        let mut f12 = vk::PhysicalDeviceVulkan12Features::default();
        let mut f13 = vk::PhysicalDeviceVulkan13Features::default();
        let mut f2 = vk::PhysicalDeviceFeatures2::default().push_next(&mut f12).push_next(&mut f13);
        // SAFETY: as above; the chain points at locals.
        unsafe { inst.get_physical_device_features2(physical, &mut f2) };
        // Core in 1.3, but each must be enabled; `discard` compiles to demote-to-helper.
        if f12.timeline_semaphore == 0
            || f13.synchronization2 == 0
            || f13.dynamic_rendering == 0
            || f13.shader_demote_to_helper_invocation == 0
        {
            return Err(VkError::Setup(format!(
                "{name} lacks timeline semaphores, synchronization2, dynamic rendering or shader demote-to-helper"
            )));
        }
        let features = DeviceFeatures {
            wireframe: supported.fill_mode_non_solid != 0,
            vertex_stores: supported.vertex_pipeline_stores_and_atomics != 0,
            pipeline_statistics: supported.pipeline_statistics_query != 0,
            clip_distance: supported.shader_clip_distance != 0,
            timestamp_period: (families[draw_family as usize].timestamp_valid_bits > 0
                && families[errors_family as usize].timestamp_valid_bits > 0)
                .then_some(properties.limits.timestamp_period),
        };
        let enabled = vk::PhysicalDeviceFeatures::default()
            .fill_mode_non_solid(features.wireframe)
            .vertex_pipeline_stores_and_atomics(features.vertex_stores)
            .pipeline_statistics_query(features.pipeline_statistics)
            .shader_clip_distance(features.clip_distance);
        let mut e12 = vk::PhysicalDeviceVulkan12Features::default().timeline_semaphore(true);
        let mut e13 = vk::PhysicalDeviceVulkan13Features::default()
            .synchronization2(true)
            .dynamic_rendering(true)
            .shader_demote_to_helper_invocation(true);
        let mut exts: Vec<*const i8> = Vec::new();
        if opts.swapchain {
            exts.push(ash::khr::swapchain::NAME.as_ptr());
        }
        // Optional: calibrated timestamps with a CPU clock Rust's Instant also uses.
        // SAFETY: queries on a live physical device.
        let available = unsafe { inst.enumerate_device_extension_properties(physical) }.unwrap_or_default();
        let has_calibration =
            available.iter().any(|e| e.extension_name_as_c_str() == Ok(ash::ext::calibrated_timestamps::NAME)) && {
                let loader = ash::ext::calibrated_timestamps::Instance::new(&instance.entry, inst);
                // SAFETY: the extension is available on this physical device.
                let domains =
                    unsafe { loader.get_physical_device_calibrateable_time_domains(physical) }.unwrap_or_default();
                domains.contains(&vk::TimeDomainEXT::DEVICE) && domains.contains(&vk::TimeDomainEXT::CLOCK_MONOTONIC)
            };
        if has_calibration {
            exts.push(ash::ext::calibrated_timestamps::NAME.as_ptr());
        }
        let info = vk::DeviceCreateInfo::default()
            .queue_create_infos(&queue_infos)
            .enabled_features(&enabled)
            .enabled_extension_names(&exts)
            .push_next(&mut e12)
            .push_next(&mut e13);
        // SAFETY: `info` only points at locals that outlive the call.
        let raw = unsafe { inst.create_device(physical, &info, None) }.vk("vkCreateDevice")?;
        // SAFETY: these queues were requested in `queue_infos`.
        let (draw_q, errors_q) = unsafe {
            match queue_mode {
                QueueMode::Shared => {
                    let q = raw.get_device_queue(draw_family, 0);
                    (q, q)
                }
                QueueMode::SeparateSameFamily => {
                    (raw.get_device_queue(draw_family, 0), raw.get_device_queue(draw_family, 1))
                }
                QueueMode::SeparateFamilies => {
                    (raw.get_device_queue(draw_family, 0), raw.get_device_queue(errors_family, 0))
                }
            }
        };
        let draw_lock = Arc::new(Mutex::new(()));
        let errors_lock = if queue_mode == QueueMode::Shared { draw_lock.clone() } else { Arc::new(Mutex::new(())) };
        let allocator = Allocator::new(&AllocatorCreateDesc {
            instance: inst.clone(),
            device: raw.clone(),
            physical_device: physical,
            debug_settings: Default::default(),
            buffer_device_address: false,
            allocation_sizes: Default::default(),
        })
        .map_err(|e| VkError::Alloc { what: "the allocator".into(), message: e.to_string() })?;
        let mut fams = vec![draw_family];
        if errors_family != draw_family {
            fams.push(errors_family);
        }
        let calibrated_timestamps =
            has_calibration.then(|| ash::ext::calibrated_timestamps::Device::new(&instance.raw, &raw));
        Ok(Arc::new(Device {
            calibrated_timestamps,
            instance,
            physical,
            raw,
            name,
            properties,
            features,
            draw_queue: Queue { handle: draw_q, family: draw_family, lock: draw_lock },
            errors_queue: Queue { handle: errors_q, family: errors_family, lock: errors_lock },
            queue_mode,
            families: fams,
            allocator: ManuallyDrop::new(Arc::new(Mutex::new(allocator))),
        }))
    }

    /// One line per optional feature this device lacks, and what degrades.
    pub fn notes(&self) -> Vec<String> {
        let mut n = Vec::new();
        if self.queue_mode == QueueMode::Shared {
            n.push(format!("{} has one graphics queue: both activities share it behind a mutex", self.name));
        }
        if self.features.timestamp_period.is_none() {
            n.push("no timestamp queries: GPU times are not reported".into());
        }
        if !self.features.clip_distance {
            n.push("no shaderClipDistance: pixels are shaded forward (--pixels forward)".into());
        }
        if !self.features.wireframe {
            n.push("no fillModeNonSolid: wireframe is unavailable".into());
        }
        n
    }

    pub fn allocator(&self) -> MutexGuard<'_, Allocator> {
        self.allocator.lock().unwrap_or_else(|e| e.into_inner())
    }

    /// The allocator itself, for a library that allocates through it. The caller must
    /// also hold an `Arc<Device>` and drop the clone first: the device frees the
    /// allocator's memory blocks when it is destroyed.
    pub fn shared_allocator(&self) -> Arc<Mutex<Allocator>> {
        Arc::clone(&self.allocator)
    }

    pub fn max_image_dimension_2d(&self) -> u32 {
        self.properties.limits.max_image_dimension2_d
    }

    pub fn wait_idle(&self) -> VkResult<()> {
        let _a = self.draw_queue.lock();
        let _b = if self.queue_mode == QueueMode::Shared { None } else { Some(self.errors_queue.lock()) };
        // SAFETY: both queues are locked, so no submission races with the wait.
        unsafe { self.raw.device_wait_idle() }.vk("vkDeviceWaitIdle")
    }
}

impl Drop for Device {
    fn drop(&mut self) {
        // SAFETY: every child holds an Arc<Device>, so all are gone; the allocator frees
        // its memory blocks before the device is destroyed.
        unsafe {
            let _ = self.raw.device_wait_idle();
            ManuallyDrop::drop(&mut self.allocator);
            self.raw.destroy_device(None);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    const G: vk::QueueFlags = vk::QueueFlags::GRAPHICS;
    const C: vk::QueueFlags = vk::QueueFlags::COMPUTE;
    const T: vk::QueueFlags = vk::QueueFlags::TRANSFER;

    #[test]
    fn queue_plans_follow_spec_section_6() {
        use QueueRequest::*;
        // lavapipe: one family, one queue.
        assert_eq!(plan_queues(&[(G | C | T, 1)], Auto), Ok((QueueMode::Shared, 0, 0)));
        assert!(plan_queues(&[(G | C | T, 1)], Separate).unwrap_err().starts_with("--queues separate"));
        // NVIDIA-like: 16 queues in the graphics family.
        assert_eq!(plan_queues(&[(G | C | T, 16), (T, 2), (C, 8)], Auto), Ok((QueueMode::SeparateSameFamily, 0, 0)));
        assert_eq!(plan_queues(&[(G | C | T, 16)], Shared), Ok((QueueMode::Shared, 0, 0)));
        // Two single-queue graphics families.
        assert_eq!(plan_queues(&[(C, 4), (G | C, 1), (G, 1)], Separate), Ok((QueueMode::SeparateFamilies, 1, 2)));
        assert!(plan_queues(&[(C | T, 2)], Auto).is_err());
    }
}
