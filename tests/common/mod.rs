//! Shared helpers for the integration tests. Every GPU test creates its device through
//! `gpu()`, which turns on validation with synchronization validation, and ends with
//! `assert_clean`, which fails on any validation message.
#![allow(dead_code)]

use std::path::PathBuf;
use std::sync::Arc;
use vkterrain::lod::heightfield::{HeightFormat, Heightfield};
use vkterrain::vk::{Device, DeviceOptions, Instance, InstanceOptions, QueueRequest};

/// `../shared/data` next to the repository. Tests that need it fail (not skip) when it
/// is missing: CI always has it.
pub fn data(rel: &str) -> PathBuf {
    let p = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../shared/data").join(rel);
    assert!(p.exists(), "test data {} is missing (expected ../shared/data beside the repository)", p.display());
    p
}

pub fn gpu_with(queues: QueueRequest) -> Arc<Device> {
    // Lavapipe's loader looks for a runtime dir; a private one keeps stderr quiet.
    if std::env::var_os("XDG_RUNTIME_DIR").is_none() {
        let dir = std::env::temp_dir().join(format!("vkterrain-xdg-{}", std::process::id()));
        let _ = std::fs::create_dir_all(&dir);
        std::env::set_var("XDG_RUNTIME_DIR", dir);
    }
    let instance = Instance::new(&InstanceOptions { validation: true, extensions: Vec::new() })
        .expect("Vulkan instance with validation (install vulkan-validationlayers)");
    Device::new(instance, &DeviceOptions { gpu: None, queues, swapchain: false }).expect("Vulkan device")
}

pub fn gpu() -> Arc<Device> {
    gpu_with(QueueRequest::Auto)
}

/// Destroys the device (it must be the last reference) and the instance, then fails on
/// any validation message, including the object tracker's reports of objects still
/// alive at vkDestroyDevice / vkDestroyInstance (leaks).
pub fn finish(device: Arc<Device>) {
    let counter = device.instance.messages.clone();
    let refs = Arc::strong_count(&device);
    assert_eq!(refs, 1, "{refs} references to the device remain: its children would leak");
    drop(device);
    assert_eq!(counter.count(), 0, "validation messages: {:#?}", counter.messages());
}

/// A crafted float heightfield.
pub fn field(
    w: usize,
    h: usize,
    spacing: impl Into<vkterrain::lod::heightfield::Spacing>,
    f: impl Fn(usize, usize) -> f32,
) -> Heightfield {
    let s: Vec<f32> = (0..w * h).map(|i| f(i % w, i / w)).collect();
    Heightfield::embed("crafted", w, h, &s, HeightFormat::Float32, spacing, 1.0).unwrap()
}

/// A crafted 16-bit heightfield (stored as R16_UNORM on the GPU).
pub fn field16(
    w: usize,
    h: usize,
    spacing: impl Into<vkterrain::lod::heightfield::Spacing>,
    scale: f32,
    f: impl Fn(usize, usize) -> u16,
) -> Heightfield {
    let s: Vec<f32> = (0..w * h).map(|i| f(i % w, i / w) as f32).collect();
    Heightfield::embed("crafted16", w, h, &s, HeightFormat::Unorm16, spacing, scale).unwrap()
}

/// Relative comparison used for GPU-vs-reference checks.
pub fn close(a: f32, b: f32, rel: f32) -> bool {
    a == b || (a - b).abs() <= rel * a.abs().max(b.abs())
}

/// A private temporary directory, removed with its contents when dropped, so that tests
/// leave nothing behind.
pub struct TempDir(PathBuf);

impl TempDir {
    pub fn new(tag: &str) -> Self {
        static NEXT: std::sync::atomic::AtomicUsize = std::sync::atomic::AtomicUsize::new(0);
        let n = NEXT.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
        let dir = std::env::temp_dir().join(format!("vkterrain-{tag}-{}-{n}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        std::fs::create_dir_all(&dir).unwrap();
        TempDir(dir)
    }
    pub fn path(&self) -> &std::path::Path {
        &self.0
    }
}

impl Drop for TempDir {
    fn drop(&mut self) {
        let _ = std::fs::remove_dir_all(&self.0);
    }
}

/// Runs `vkterrain ARGS` (RUST_LOG=error, stdout and stderr captured) and fails the test
/// if it is still running after `limit_s` seconds: a bad input must end a run, never
/// block it (a FIFO read would).
pub fn run_bounded(args: &[String], limit_s: u64) -> std::process::Output {
    let mut child = std::process::Command::new(env!("CARGO_BIN_EXE_vkterrain"))
        .args(args)
        .env("RUST_LOG", "error")
        .stdout(std::process::Stdio::piped())
        .stderr(std::process::Stdio::piped())
        .spawn()
        .expect("run vkterrain");
    let started = std::time::Instant::now();
    // Polling the child's state (not a fixed sleep standing in for synchronisation).
    while child.try_wait().unwrap().is_none() {
        if started.elapsed() > std::time::Duration::from_secs(limit_s) {
            let _ = child.kill();
            let _ = child.wait();
            panic!("{args:?}: still running after {limit_s} s (a hang)");
        }
        std::thread::sleep(std::time::Duration::from_millis(20));
    }
    child.wait_with_output().unwrap()
}
