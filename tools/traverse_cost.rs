//! The draw thread's traversal timed on the CPU alone, with no GPU and no Vulkan: block
//! selection, the morph's factors and the occlusion sweep over a camera path, with the
//! error data from the CPU reference (which the GPU's matches texel for texel). What
//! `bench` reports as `traverse_ms`, without the rasterizer's threads beside it, so that
//! `perf` sees the traversal alone (docs/profiling.md, "The traversal alone").
//!
//! ```sh
//! source tools/env.sh && bash tools/cargo.sh run --example traverse_cost -- \
//!   --heightmap fbm4097.png --spacing 1 \
//!   --height-scale 0.0333333 --fovy 45 --size 1280x720 --path turn.txt
//! ```
//!
//! It prints the median and slowest frames' times and a hash of every frame's selection
//! (blocks, LODs, morph factors), which a change that should leave the selection alone
//! must leave alone.

use clap::Parser;
use glam::Vec3;
use std::path::PathBuf;
use std::time::Instant;
use vkterrain::app::paths::{path_camera, CameraPath};
use vkterrain::input::load::{load, LoadOptions};
use vkterrain::lod::block::BlockLayout;
use vkterrain::lod::camera::Camera;
use vkterrain::lod::gie::{block_errors, group_errors, BlockErrors, ErrorMode, ErrorParams};
use vkterrain::lod::morph;
use vkterrain::lod::occlusion::Probe;
use vkterrain::lod::pyramid::MinMaxPyramid;
use vkterrain::lod::traversal::{traverse, BlockCaches, LodSelect};

#[derive(Parser)]
struct Args {
    #[arg(long)]
    heightmap: PathBuf,
    /// Metres between samples (default: what the file says).
    #[arg(long)]
    spacing: Option<f32>,
    /// Metres per height unit (default: what the file says).
    #[arg(long)]
    height_scale: Option<f32>,
    /// A pose file (`cx cy cz lx ly lz` a line), or `paper-flyover`.
    #[arg(long, default_value = "paper-flyover")]
    path: String,
    /// Frames over the paper flyover (`bench --frames`: 60 frames take larger steps, so
    /// more blocks are new each frame).
    #[arg(long, default_value_t = 600)]
    frames: usize,
    #[arg(long, default_value_t = 60.0)]
    fovy: f32,
    #[arg(long, default_value = "640x480")]
    size: String,
    #[arg(long, default_value_t = 33)]
    block: u32,
    #[arg(long, default_value_t = 1.0)]
    delta: f32,
    /// New error data every this many frames (computed at that frame's camera).
    #[arg(long, default_value_t = 10)]
    refresh: usize,
    /// Run the occlusion sweep (with the renderer's probe).
    #[arg(long)]
    occlusion: bool,
    /// GPU nanoseconds per triangle the probe is told (default: none, so it judges by
    /// the share of parts hidden).
    #[arg(long)]
    triangle_ns: Option<f64>,
    /// Threads for the per-block work (default: every core).
    #[arg(long)]
    threads: Option<usize>,
}

fn main() -> anyhow::Result<()> {
    let a = Args::parse();
    let (w, h) = a.size.split_once('x').ok_or_else(|| anyhow::anyhow!("--size WxH"))?;
    let (w, h): (u32, u32) = (w.parse()?, h.parse()?);
    let opts = LoadOptions { spacing: a.spacing.map(Into::into), height_scale: a.height_scale, ..Default::default() };
    let hf = load(&a.heightmap, &opts)?;
    let mm = MinMaxPyramid::build(&hf);
    let layout = BlockLayout::of(&hf, a.block).map_err(anyhow::Error::msg)?;
    let near = vkterrain::lod::view::near_plane(&hf);
    let cams: Vec<Camera> = if a.path == "paper-flyover" {
        (0..a.frames)
            .map(|i| path_camera(&hf, &mm, CameraPath::PaperFlyover, i as u64, a.frames as u64, a.fovy, (w, h)).0)
            .collect()
    } else {
        let poses = vkterrain::app::bench::read_poses(std::path::Path::new(&a.path))?;
        poses.iter().map(|(c, l)| Camera::look_at(*c, *l, a.fovy, w, h, near)).collect()
    };
    let refresh = a.refresh.max(1);
    let generations: Vec<(Vec3, BlockErrors)> = cams
        .iter()
        .step_by(refresh)
        .map(|c| (c.position, block_errors(&group_errors(&hf, &mm, &ErrorParams::new(c, ErrorMode::Strict)), layout.m)))
        .collect();
    let pool = rayon::ThreadPoolBuilder::new().num_threads(a.threads.unwrap_or(0)).build()?;
    let caches = BlockCaches::default();
    let mut probe = Probe::default();
    let (mut frames, mut hash, mut sweeps) = (Vec::new(), 0u64, Vec::new());
    for (i, cam) in cams.iter().enumerate() {
        let (at, errors) = &generations[i / refresh];
        let select = LodSelect::errors(errors, *at, a.delta, ErrorMode::Strict);
        let t0 = Instant::now();
        let mut t = pool.install(|| traverse(&hf, &mm, &caches, &layout, cam, select.with_morph(false)));
        let t1 = Instant::now();
        pool.install(|| morph::assign(&hf, &mm, &caches, &layout, cam, a.delta, &mut t));
        let t2 = Instant::now();
        if a.occlusion {
            if let Some(ns) = a.triangle_ns {
                // One frame of a million triangles at `ns` each.
                probe.observe(Some(ns), 1_000_000);
            }
            if probe.cull(&hf, &mm, &caches, &layout, cam, &mut t).skipped.is_none() {
                sweeps.push(t2.elapsed().as_secs_f64() * 1e3);
            }
        }
        let ms = |from: Instant, to: Instant| (to - from).as_secs_f64() * 1e3;
        frames.push((ms(t0, t1), ms(t1, t2), ms(t0, Instant::now()), t.blocks.len()));
        for b in &t.blocks {
            for v in [b.lod, b.bx, b.bz, b.morph as u32, b.hidden_parts as u32]
                .into_iter()
                .chain(b.edge_morph.map(u32::from))
            {
                hash = hash.wrapping_mul(0x100_0000_01b3).wrapping_add(v as u64 + 1);
            }
        }
    }
    let first = frames.remove(0);
    println!("first frame (caches cold): {:.2} ms", first.2);
    // The mean, split: the figure to compare builds by (single frames are noisy).
    let n = frames.len().max(1) as f64;
    let mean = |f: fn(&(f64, f64, f64, usize)) -> f64| frames.iter().map(f).sum::<f64>() / n;
    println!("    mean: {:.2} ms (select {:.2}, morph {:.2})", mean(|f| f.2), mean(|f| f.0), mean(|f| f.1));
    frames.sort_by(|a, b| a.2.total_cmp(&b.2));
    let at = |q: f64| frames[((frames.len() - 1) as f64 * q).round() as usize];
    for (name, f) in [("median", at(0.5)), ("p99", at(0.99)), ("slowest", at(1.0))] {
        println!("{name:>8}: {:.2} ms (select {:.2}, morph {:.2}), {} blocks", f.2, f.0, f.1, f.3);
    }
    if a.occlusion {
        let mean = sweeps.iter().sum::<f64>() / sweeps.len().max(1) as f64;
        println!("sweeps: {} of {} frames, {mean:.2} ms each", sweeps.len(), frames.len() + 1);
    }
    println!("threads {}, selection hash {hash:016x}", pool.current_num_threads());
    Ok(())
}
