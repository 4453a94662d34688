//! The layer's one error type: a failed call or allocation, with where it happened.

use ash::vk;
use std::backtrace::Backtrace;

/// A failed Vulkan call or allocation, with where it happened.
#[derive(Clone, Debug, thiserror::Error)]
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
    /// The device cannot satisfy a command-line option (`--gpu`, `--queues`): the
    /// user's input, not a failure of the device (exit code 2).
    #[error("{0}")]
    Option(String),
    /// A failure on another thread (the errors activity), kept whole across the thread
    /// boundary so that the caller still sees, e.g., the device loss. The message holds
    /// the cause, so it is not also a `source()` (`{:#}` would print it twice more).
    #[error("{stage}: {cause}")]
    Thread { stage: String, cause: Box<VkError> },
}

impl VkError {
    /// True when the device was lost (the caller names the stage and stops).
    pub fn is_device_lost(&self) -> bool {
        match self {
            VkError::Call { result, .. } => *result == vk::Result::ERROR_DEVICE_LOST,
            VkError::Thread { cause, .. } => cause.is_device_lost(),
            _ => false,
        }
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

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn device_loss_survives_the_thread_boundary() {
        let lost = Err::<(), _>(vk::Result::ERROR_DEVICE_LOST).vk("vkQueueSubmit2").unwrap_err();
        let wrapped = VkError::Thread {
            stage: "errors activity".into(),
            cause: Box::new(VkError::Thread { stage: "generation 5".into(), cause: Box::new(lost) }),
        };
        assert!(wrapped.is_device_lost());
        assert_eq!(wrapped.to_string(), "errors activity: generation 5: vkQueueSubmit2 failed: ERROR_DEVICE_LOST");
        // Printed with its chain (as main does), the cause appears once.
        let chain = format!("{:#}", anyhow::Error::from(wrapped.clone()));
        assert_eq!(chain.matches("ERROR_DEVICE_LOST").count(), 1, "{chain}");
        assert!(!VkError::Option("--gpu x".into()).is_device_lost());
        let anyhow_err = anyhow::Error::from(wrapped.clone());
        assert!(anyhow_err.downcast_ref::<VkError>().is_some_and(VkError::is_device_lost));
    }
}
