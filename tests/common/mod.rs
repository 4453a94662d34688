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
    run_bounded_logging(args, limit_s, Some("error"))
}

/// [`run_bounded`] with `RUST_LOG` set to `log`, or unset (`None`: as a user runs it).
pub fn run_bounded_logging(args: &[String], limit_s: u64, log: Option<&str>) -> std::process::Output {
    let mut command = std::process::Command::new(env!("CARGO_BIN_EXE_vkterrain"));
    match log {
        Some(l) => command.env("RUST_LOG", l),
        None => command.env_remove("RUST_LOG"),
    };
    let mut child = command
        .args(args)
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

/// `vkterrain ARGS` as a test runs it: [`run_bounded`] with room for a slow machine.
#[allow(dead_code)]
pub fn cli(args: &[&str]) -> std::process::Output {
    run_bounded(&args.iter().map(|a| a.to_string()).collect::<Vec<_>>(), 600)
}

/// Every drawn edge vertex lies on the neighbour's surface: for LOD differences up to m
/// it coincides with one of the neighbour's vertices (same sample, same height).
/// Every sample on the boundary between two drawn blocks has the same rendered height in
/// both (stitched and morphed): no crack. Returns the samples compared.
#[allow(dead_code)]
pub fn assert_watertight<S: vkterrain::lod::heightfield::RawSamples>(
    hf: &S,
    extent: [usize; 2],
    layout: &vkterrain::lod::block::BlockLayout,
    blocks: &[vkterrain::lod::block::DrawBlock],
    lod_map: &[i8],
    what: &str,
) -> usize {
    let [cells, rows] = layout.cells().map(|c| c as i64);
    let cell = 1i64 << layout.m;
    let at = |cx: i64, cz: i64| -> Option<usize> {
        if cx < 0 || cz < 0 || cx >= cells || cz >= rows {
            return None;
        }
        let l = lod_map[(cz * cells + cx) as usize];
        if l < 0 {
            return None;
        }
        let l = l as u32;
        blocks.iter().position(|b| b.lod == l && b.bx as i64 == cx >> l && b.bz as i64 == cz >> l)
    };
    let mut compared = 0;
    for (i, b) in blocks.iter().enumerate() {
        let (ox, oz) = b.origin(layout);
        let side = layout.block_samples(b.lod) as i64;
        let (ox, oz) = (ox as i64, oz as i64);
        // Samples along the north and west edges, shared with the block across.
        for d in 0..=side {
            for (x, z, across) in [
                (ox + d, oz, (ox + d - (d == side) as i64, oz - 1)),
                (ox, oz + d, (ox - 1, oz + d - (d == side) as i64)),
            ] {
                if x >= extent[0] as i64 || z >= extent[1] as i64 {
                    continue;
                }
                let Some(j) = at(across.0.div_euclid(cell), across.1.div_euclid(cell)) else { continue };
                if j == i {
                    continue;
                }
                let mine = vkterrain::lod::audit::rendered_raw(hf, layout, b, x, z);
                let theirs = vkterrain::lod::audit::rendered_raw(hf, layout, &blocks[j], x, z);
                let (Some(a), Some(c)) = (mine, theirs) else {
                    panic!("{what}: sample ({x}, {z}) on the edge of {b:?} and {:?} not covered", blocks[j])
                };
                assert!(
                    (a - c).abs() <= 1e-5 * (1.0 + a.abs().max(c.abs())),
                    "{what}: crack at ({x}, {z}): {a} in {b:?}, {c} in {:?}",
                    blocks[j]
                );
                compared += 1;
            }
        }
    }
    compared
}

/// A rough square field of `2^10 + 1` samples (so that the in-memory grid and the
/// archive's quadtree coincide): value noise, a ridge, a cliff and one spike.
#[allow(dead_code)]
pub fn rough() -> Heightfield {
    let side = 1025;
    field(side, side, [3.0, 5.0], |x, z| {
        let n = ((x * 7919 + z * 104_729) % 1013) as f32 * 0.002;
        let ridge = 40.0 - ((x as f32 - 0.6 * z as f32).abs() * 0.3).min(40.0);
        let cliff = if x > 610 && z < 400 { 70.0 } else { 0.0 };
        let spike = if (x, z) == (700, 333) { 900.0 } else { 0.0 };
        n + ridge + cliff + spike + ((x as f32 * 0.013).sin() * (z as f32 * 0.021).cos()) * 60.0
    })
}

/// `hf` prepared into an archive in `dir`.
#[allow(dead_code)]
pub fn archive_of(hf: &Heightfield, dir: &TempDir) -> Arc<vkterrain::input::archive::Archive> {
    let out = dir.path().join("t.pmtiles");
    let frame = vkterrain::prepare::Frame {
        spacing: [hf.spacing.x, hf.spacing.z],
        height_scale: hf.height_scale,
        georef: hf.georef.clone(),
        void_samples: 0,
    };
    vkterrain::prepare::prepare(
        &vkterrain::prepare::source::InMemory(hf),
        &frame,
        &out,
        &|_, _| {},
        &std::sync::atomic::AtomicBool::new(false),
    )
    .expect("prepare");
    Arc::new(vkterrain::input::archive::Archive::open(&out).expect("open"))
}

/// Pixels of a frame that are not sky: the sky is drawn as a gradient from the horizon
/// colour to the zenith's (`draw::blocks::SKY_*`, stored sRGB-encoded), so a pixel within
/// a few levels of any colour along it counts as sky (terrain fogged out to the horizon
/// colour too).
pub fn terrain_pixels(img: &image::RgbaImage) -> usize {
    use vkterrain::draw::blocks::{SKY_HORIZON, SKY_ZENITH};
    let srgb = |c: f32| {
        let s = if c <= 0.003_130_8 { c * 12.92 } else { 1.055 * c.powf(1.0 / 2.4) - 0.055 };
        (s * 255.0).round()
    };
    let sky: Vec<[f32; 3]> = (0..=256)
        .map(|i| {
            let t = i as f32 / 256.0;
            [0, 1, 2].map(|k| srgb(SKY_HORIZON[k] + (SKY_ZENITH[k] - SKY_HORIZON[k]) * t))
        })
        .collect();
    img.pixels().filter(|p| !sky.iter().any(|s| (0..3).all(|k| (f32::from(p[k]) - s[k]).abs() <= 3.0))).count()
}

/// Drawn surface height (raw) at every sample `blocks` cover, NaN where nothing is drawn.
pub fn drawn_surface(
    hf: &Heightfield,
    layout: &vkterrain::lod::block::BlockLayout,
    blocks: &[vkterrain::lod::block::DrawBlock],
) -> Vec<f32> {
    let mut h = vec![f32::NAN; hf.width * hf.height];
    for b in blocks {
        let (ox, oz) = b.origin(layout);
        let side = layout.block_samples(b.lod) as usize;
        for z in oz as usize..(oz as usize + side + 1).min(hf.height) {
            for x in ox as usize..(ox as usize + side + 1).min(hf.width) {
                if let Some(r) = vkterrain::lod::audit::rendered_raw(hf, layout, b, x as i64, z as i64) {
                    h[z * hf.width + x] = r;
                }
            }
        }
    }
    h
}

/// Screen motion between two drawn surfaces ([`drawn_surface`]) seen by `cam`: over
/// every sample drawn in both, inside the frustum, the squared pixel distance between
/// its two drawn points, weighted by the screen area of a sample spacing there.
pub fn surface_motion(hf: &Heightfield, cam: &vkterrain::lod::camera::Camera, before: &[f32], now: &[f32]) -> f64 {
    assert_eq!(now.len(), before.len(), "surfaces of two frames");
    let vp = cam.view_proj();
    let frustum = cam.frustum();
    let mut energy = 0.0f64;
    for (i, (&a, &b)) in now.iter().zip(before).enumerate() {
        if a.is_nan() || b.is_nan() || a == b {
            continue;
        }
        let (x, z) = ((i % hf.width) as f32 * hf.spacing.x, (i / hf.width) as f32 * hf.spacing.z);
        let pa = glam::Vec3::new(x, a * hf.height_scale, z);
        let pb = glam::Vec3::new(x, b * hf.height_scale, z);
        if !frustum.contains_point(pa) || !frustum.contains_point(pb) {
            continue;
        }
        if let (Some(qa), Some(qb)) = (cam.project(&vp, pa), cam.project(&vp, pb)) {
            let area = (hf.spacing.min() * cam.kappa() / (pa - cam.position).length()).powi(2).min(1e4);
            energy += (((qa.0 - qb.0).powi(2) + (qa.1 - qb.1).powi(2)) * area) as f64;
        }
    }
    energy
}

/// What a run stopped by a signal left: its exit status and everything it printed.
pub struct Stopped {
    pub status: std::process::ExitStatus,
    /// From the signal to the run's end.
    pub after_signal: std::time::Duration,
    pub stdout: String,
    pub stderr: String,
}

/// Runs `vkterrain ARGS`, sends it `SIG{signal}` (`INT`, `TERM`) once `ready` says so, and
/// returns how it ended. `ready` sees each line printed (on either stream), and `None`
/// every 50 ms between lines (to poll a file). Fails the test if it is not ready within
/// 300 s, or if the run has not ended 120 s after the signal.
pub fn stop_with_signal(args: &[&str], ready: impl Fn(Option<&str>) -> bool, signal: &str) -> Stopped {
    use std::io::BufRead;
    let mut child = std::process::Command::new(env!("CARGO_BIN_EXE_vkterrain"))
        .args(args)
        .env("RUST_LOG", "error")
        .stdout(std::process::Stdio::piped())
        .stderr(std::process::Stdio::piped())
        .spawn()
        .expect("run vkterrain");
    let (tx, rx) = std::sync::mpsc::channel::<String>();
    let reader = |pipe: Box<dyn std::io::Read + Send>, tx: std::sync::mpsc::Sender<String>| {
        std::thread::spawn(move || {
            let mut all = String::new();
            for line in std::io::BufReader::new(pipe).lines().map_while(Result::ok) {
                let _ = tx.send(line.clone());
                all += &line;
                all.push('\n');
            }
            all
        })
    };
    let out = reader(Box::new(child.stdout.take().unwrap()), tx.clone());
    let err = reader(Box::new(child.stderr.take().unwrap()), tx);
    let limit = std::time::Instant::now() + std::time::Duration::from_secs(300);
    let mut seen = Vec::new();
    loop {
        let line = match rx.recv_timeout(std::time::Duration::from_millis(50)) {
            Ok(line) => Some(line),
            Err(std::sync::mpsc::RecvTimeoutError::Timeout) => None,
            Err(std::sync::mpsc::RecvTimeoutError::Disconnected) => {
                let status = child.wait().unwrap();
                panic!("{args:?}: ended ({status}) before it was ready: {seen:#?}");
            }
        };
        if ready(line.as_deref()) {
            break;
        }
        seen.extend(line);
        if std::time::Instant::now() > limit {
            let _ = child.kill();
            panic!("{args:?}: not ready in 300 s: {seen:#?}");
        }
    }
    let sent = std::process::Command::new("kill").args([&format!("-{signal}"), &child.id().to_string()]).status();
    assert!(sent.is_ok_and(|s| s.success()), "kill -{signal}");
    let started = std::time::Instant::now();
    // Polling the child's state (not a fixed sleep standing in for synchronisation).
    let status = loop {
        if let Some(s) = child.try_wait().unwrap() {
            break s;
        }
        if started.elapsed() > std::time::Duration::from_secs(120) {
            let _ = child.kill();
            panic!("{args:?}: still running 120 s after SIG{signal}");
        }
        std::thread::sleep(std::time::Duration::from_millis(20));
    };
    let after_signal = started.elapsed();
    Stopped { status, after_signal, stdout: out.join().unwrap(), stderr: err.join().unwrap() }
}

/// The exit code a shell reports for a run ended by `SIG{signal}`: 128 + the signal.
pub fn signal_code(signal: &str) -> i32 {
    128 + match signal {
        "INT" => 2,
        "TERM" => 15,
        "HUP" => 1,
        other => panic!("no code for SIG{other}"),
    }
}

/// A small 16-bit PNG of hills, `side` samples a side: quick to load and draw.
pub fn hills_png(dir: &std::path::Path, side: u32) -> PathBuf {
    let p = dir.join("hills.png");
    image::ImageBuffer::<image::Luma<u16>, _>::from_fn(side, side, |x, z| {
        let (x, z) = (x as f32, z as f32);
        image::Luma([(20000.0 + 8000.0 * (x * 0.07).sin() * (z * 0.05).cos()) as u16])
    })
    .save(&p)
    .unwrap();
    p
}

/// The JSON a command printed: all of `text` (pretty-printed), else its last line that
/// parses as JSON.
pub fn json_in(text: &str) -> serde_json::Value {
    serde_json::from_str(text)
        .ok()
        .or_else(|| text.lines().rev().find_map(|l| serde_json::from_str(l).ok()))
        .unwrap_or_else(|| panic!("no JSON in: {text}"))
}
