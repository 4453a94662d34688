//! What leaving out the parts of streamed blocks outside the frustum buys: a low flight
//! over an archive (the `stream` command's line, 200 units above the ground, looking
//! ahead and a little down), each settled frame drawn twice on the GPU from the atlas,
//! whole and with those parts left out, in alternating order; the frame times, the
//! triangles and the share of parts left out, as one JSON line.
//!
//! ```sh
//! source tools/env.sh && bash tools/run.sh prepare --synthetic 4097 --out s.pmtiles && \
//!   bash tools/cargo.sh run --example streamed_parts_cost -- s.pmtiles --frames 60
//! ```

use clap::Parser;
use glam::DVec3;
use std::path::PathBuf;
use std::sync::Arc;
use std::time::Instant;
use vkterrain::draw::streamed::{FrameView, HeightRange, StreamedRenderer};
use vkterrain::errors::atlas::HeightAtlas;
use vkterrain::input::archive::Archive;
use vkterrain::stream::draw;
use vkterrain::stream::streamer::Streamer;
use vkterrain::stream::traverse::View;
use vkterrain::stream::Grid;
use vkterrain::vk::{Device, DeviceOptions, Instance, InstanceOptions, QueueRequest};

#[derive(Parser)]
struct Args {
    /// An archive written by `vkterrain prepare`.
    archive: PathBuf,
    /// Poses along the flight.
    #[arg(long, default_value_t = 60)]
    frames: u32,
    /// Viewport, pixels.
    #[arg(long, default_value_t = 1280)]
    width: u32,
    #[arg(long, default_value_t = 720)]
    height: u32,
    /// Height above the ground, world units.
    #[arg(long, default_value_t = 200.0)]
    altitude: f64,
}

fn median(mut v: Vec<f64>) -> f64 {
    v.sort_by(f64::total_cmp);
    v[v.len() / 2]
}

fn main() -> anyhow::Result<()> {
    let args = Args::parse();
    anyhow::ensure!(args.frames >= 1, "--frames must be at least 1");
    let archive = Arc::new(Archive::open(&args.archive)?);
    let grid = Grid::from_meta(&archive.meta);
    let instance = Instance::new(&InstanceOptions { validation: false, extensions: Vec::new() })?;
    let device: Arc<Device> =
        Device::new(instance, &DeviceOptions { gpu: None, queues: QueueRequest::Auto, swapchain: false })?;
    let (whole_ms, culled_ms, tris, hidden_share) = {
        let mut s = Streamer::new(archive, grid, 1 << 30);
        let atlas = HeightAtlas::new(&device, &grid, 512 << 20)?;
        s.attach(Box::new(atlas.feed()), HeightAtlas::cache_tiles(atlas.layer_count()));
        let lit = vkterrain::draw::lighting_gpu::OwnLighting::everything_lit(&device)?;
        let mut renderer = StreamedRenderer::new(&device, draw::layout(&grid), args.width, args.height)?;
        let extent = grid.world_extent();
        let start = DVec3::new(0.05 * extent[0], 0.0, 0.05 * extent[1]);
        let along = DVec3::new(0.9 * extent[0], 0.0, 0.9 * extent[1]);
        let (mut whole_ms, mut culled_ms, mut tris, mut parts) = (Vec::new(), Vec::new(), [0u64; 2], [0u64; 2]);
        for f in 0..args.frames {
            let at = start + along * (f64::from(f) + 0.5) / f64::from(args.frames);
            let ground = s.ground(at.x, at.z).unwrap_or(0.0);
            let position = DVec3::new(at.x, ground + args.altitude, at.z);
            let target = position + along.normalize() * 1000.0 + DVec3::new(0.0, -150.0, 0.0);
            let view = View::look_at(position, target, 45.0, args.width, args.height, 1.0);
            // Settled: every tile the view wants is held (the ground above is refined too).
            let mut sel = s.frame(&view, None, 1.0, 1.0);
            for _ in 0..16 {
                if sel.within_bound() {
                    break;
                }
                s.settle();
                sel = s.frame(&view, None, 1.0, 1.0);
            }
            let whole = draw::stitched_blocks(&grid, &s.cache, &sel);
            let (anchor, cam) = view.relative(&grid);
            let mut culled = whole.clone();
            draw::hide_parts_outside(&grid, &s.cache, anchor, &cam, &mut culled);
            let fv = FrameView {
                grid: &grid,
                anchor,
                cam,
                heights: HeightRange { world: [0.0, 1000.0], absolute: false },
                fog: 0.0,
                light: glam::Vec3::Y,
                lighting: &lit,
                colour_by_lod: false,
                wireframe: false,
                background: None,
            };
            // Alternating which goes first, so that neither always follows the other.
            for (i, blocks) in if f % 2 == 0 { [&whole, &culled] } else { [&culled, &whole] }.into_iter().enumerate() {
                let t = Instant::now();
                let stats = renderer.render_unread(&atlas, &fv, blocks)?;
                let ms = t.elapsed().as_secs_f64() * 1e3;
                let is_whole = (i == 0) == (f % 2 == 0);
                let k = usize::from(!is_whole);
                if is_whole {
                    whole_ms.push(ms)
                } else {
                    culled_ms.push(ms)
                };
                tris[k] += stats.triangles;
                parts[k] += stats.hidden_parts;
                if is_whole {
                    parts[0] += stats.blocks as u64 * u64::from(draw::layout(&grid).parts_per_side().pow(2));
                }
            }
        }
        (whole_ms, culled_ms, tris, parts[1] as f64 / parts[0].max(1) as f64)
    };
    let (w, c) = (median(whole_ms), median(culled_ms));
    println!(
        "{}",
        serde_json::json!({
            "archive": args.archive.display().to_string(),
            "frames": args.frames,
            "size": [args.width, args.height],
            "device": device.name,
            "median_ms_whole": w,
            "median_ms_parts_left_out": c,
            "whole_over_parts_left_out": w / c,
            "mean_triangles_whole": tris[0] as f64 / f64::from(args.frames),
            "mean_triangles_parts_left_out": tris[1] as f64 / f64::from(args.frames),
            "parts_left_out_share": hidden_share,
        })
    );
    Ok(())
}
