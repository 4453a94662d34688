//! Instance, validation layers (with synchronization validation) and the debug messenger
//! that counts every warning and error.

use super::error::{VkError, VkResult, VkResultExt};
use ash::vk;
use std::ffi::{c_void, CStr};
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex};

const VALIDATION_LAYER: &CStr = c"VK_LAYER_KHRONOS_validation";

/// Counts validation warnings and errors; keeps the first few for reports.
#[derive(Default, Debug)]
pub struct MessageCounter {
    count: AtomicU64,
    first: Mutex<Vec<String>>,
}

impl MessageCounter {
    pub fn count(&self) -> u64 {
        self.count.load(Ordering::SeqCst)
    }
    pub fn messages(&self) -> Vec<String> {
        self.first.lock().unwrap().clone()
    }
    fn record(&self, text: String) {
        self.count.fetch_add(1, Ordering::SeqCst);
        let mut first = self.first.lock().unwrap();
        if first.len() < 32 {
            first.push(text);
        }
    }
}

#[derive(Clone, Debug, Default)]
pub struct InstanceOptions {
    pub validation: bool,
    /// Extra instance extensions (surface extensions for a window).
    pub extensions: Vec<&'static CStr>,
}

pub struct Instance {
    pub entry: ash::Entry,
    pub raw: ash::Instance,
    debug: Option<(ash::ext::debug_utils::Instance, vk::DebugUtilsMessengerEXT)>,
    /// Boxed inside an Arc so its address, handed to the messenger, stays put.
    pub messages: Arc<MessageCounter>,
    pub validation: bool,
}

unsafe extern "system" fn debug_callback(
    severity: vk::DebugUtilsMessageSeverityFlagsEXT,
    _types: vk::DebugUtilsMessageTypeFlagsEXT,
    data: *const vk::DebugUtilsMessengerCallbackDataEXT<'_>,
    user: *mut c_void,
) -> vk::Bool32 {
    // SAFETY: the loader passes valid callback data for the duration of the call, and
    // `user` is the MessageCounter that the Instance keeps alive until the messenger is
    // destroyed.
    let (text, counter) = unsafe {
        let msg = if data.is_null() || (*data).p_message.is_null() {
            "(no message)".to_string()
        } else {
            CStr::from_ptr((*data).p_message).to_string_lossy().into_owned()
        };
        (msg, &*(user as *const MessageCounter))
    };
    if severity.contains(vk::DebugUtilsMessageSeverityFlagsEXT::ERROR) {
        tracing::error!(target: "vulkan", "{text}");
        counter.record(text);
    } else if severity.contains(vk::DebugUtilsMessageSeverityFlagsEXT::WARNING) {
        tracing::warn!(target: "vulkan", "{text}");
        counter.record(text);
    } else {
        tracing::debug!(target: "vulkan", "{text}");
    }
    vk::FALSE
}

impl Instance {
    pub fn new(opts: &InstanceOptions) -> VkResult<Arc<Self>> {
        // SAFETY: loading the system Vulkan loader; its symbols are used only through ash.
        let entry = unsafe { ash::Entry::load() }.map_err(|e| {
            VkError::Setup(format!(
                "cannot load the Vulkan loader ({e}); install libvulkan1 and a driver (mesa-vulkan-drivers for lavapipe)"
            ))
        })?;
        // SAFETY: plain enumeration calls on a loaded entry.
        let layers = unsafe { entry.enumerate_instance_layer_properties() }.vk("vkEnumerateInstanceLayerProperties")?;
        let has_layer = layers.iter().any(|l| l.layer_name_as_c_str().is_ok_and(|n| n == VALIDATION_LAYER));
        if opts.validation && !has_layer {
            return Err(VkError::Setup(
                "validation was requested but VK_LAYER_KHRONOS_validation is not installed (Debian: vulkan-validationlayers); use --validation off to run without it".into(),
            ));
        }
        let app_name = c"vkterrain";
        let app = vk::ApplicationInfo::default()
            .application_name(app_name)
            .engine_name(app_name)
            .api_version(vk::API_VERSION_1_3);
        let mut ext: Vec<*const i8> = opts.extensions.iter().map(|e| e.as_ptr()).collect();
        let mut layer_ptrs = Vec::new();
        if opts.validation {
            layer_ptrs.push(VALIDATION_LAYER.as_ptr());
            ext.push(ash::ext::debug_utils::NAME.as_ptr());
            ext.push(ash::ext::validation_features::NAME.as_ptr());
        }
        let enables = [vk::ValidationFeatureEnableEXT::SYNCHRONIZATION_VALIDATION];
        let mut features = vk::ValidationFeaturesEXT::default().enabled_validation_features(&enables);
        let counter = Arc::new(MessageCounter::default());
        let severity = vk::DebugUtilsMessageSeverityFlagsEXT::ERROR
            | vk::DebugUtilsMessageSeverityFlagsEXT::WARNING
            | vk::DebugUtilsMessageSeverityFlagsEXT::INFO;
        let types = vk::DebugUtilsMessageTypeFlagsEXT::GENERAL
            | vk::DebugUtilsMessageTypeFlagsEXT::VALIDATION
            | vk::DebugUtilsMessageTypeFlagsEXT::PERFORMANCE;
        let mut messenger_info = vk::DebugUtilsMessengerCreateInfoEXT::default()
            .message_severity(severity)
            .message_type(types)
            .pfn_user_callback(Some(debug_callback))
            .user_data(Arc::as_ptr(&counter) as *mut c_void);
        let mut info = vk::InstanceCreateInfo::default()
            .application_info(&app)
            .enabled_layer_names(&layer_ptrs)
            .enabled_extension_names(&ext);
        if opts.validation {
            // Chained here too so that messages from instance creation are counted.
            info = info.push_next(&mut features).push_next(&mut messenger_info);
        }
        // SAFETY: every pointer in `info` refers to locals that outlive the call.
        let raw = unsafe { entry.create_instance(&info, None) }.vk("vkCreateInstance")?;
        let debug = if opts.validation {
            let loader = ash::ext::debug_utils::Instance::new(&entry, &raw);
            let messenger_info = vk::DebugUtilsMessengerCreateInfoEXT::default()
                .message_severity(severity)
                .message_type(types)
                .pfn_user_callback(Some(debug_callback))
                .user_data(Arc::as_ptr(&counter) as *mut c_void);
            // SAFETY: the counter outlives the messenger (destroyed first in Drop).
            let m = unsafe { loader.create_debug_utils_messenger(&messenger_info, None) }
                .vk("vkCreateDebugUtilsMessengerEXT")?;
            Some((loader, m))
        } else {
            None
        };
        Ok(Arc::new(Instance { entry, raw, debug, messages: counter, validation: opts.validation }))
    }

    pub fn validation_messages(&self) -> u64 {
        self.messages.count()
    }
}

impl Drop for Instance {
    fn drop(&mut self) {
        // SAFETY: every child object holds an Arc<Instance> through its Device, so none is
        // alive here; the messenger goes first, the instance last.
        unsafe {
            if let Some((loader, m)) = self.debug.take() {
                loader.destroy_debug_utils_messenger(m, None);
            }
            self.raw.destroy_instance(None);
        }
    }
}

/// Turns a fixed-size C string from Vulkan into a Rust string.
pub(crate) fn c_name(raw: &[i8]) -> String {
    // SAFETY: Vulkan guarantees these arrays are NUL-terminated.
    unsafe { CStr::from_ptr(raw.as_ptr()) }.to_string_lossy().into_owned()
}
