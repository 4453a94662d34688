//! The hand-off between the errors thread and a reader (SPEC section 4): a scripted
//! camera moving fast drives hundreds of generations while a reader thread consumes
//! them, on one shared queue, under synchronization validation.

mod common;
use common::*;
use glam::Vec3;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant};
use vkterrain::camera::Camera;
use vkterrain::errors_activity::ErrorsActivity;
use vkterrain::gie::{block_errors, group_errors, ErrorMode, ErrorParams};
use vkterrain::heightfield::MinMaxPyramid;
use vkterrain::quadtree::BlockLayout;
use vkterrain::terrain_gpu::TerrainGpu;
use vkterrain::vk::{QueueMode, QueueRequest};

const GENERATIONS: u64 = 300;

#[test]
fn hundreds_of_generations_reach_a_concurrent_reader() {
    let device = gpu_with(QueueRequest::Shared);
    assert_eq!(device.queue_mode, QueueMode::Shared);
    let hf =
        field(129, 129, 2.0, |x, z| ((x as f32 * 0.21).sin() * (z as f32 * 0.17).cos()) * 15.0 + ((x * z) % 7) as f32);
    let mm = MinMaxPyramid::build(&hf);
    let layout = BlockLayout::new(hf.n, 9).unwrap();
    let terrain = Arc::new(TerrainGpu::new(&device, &hf, &mm, None, None).unwrap());
    let hf = Arc::new(hf);
    let activity = Arc::new(ErrorsActivity::start(&device, terrain, hf.clone(), layout).unwrap());
    let camera_at = |i: u64| {
        // A fast flyover: a new position every step.
        let t = i as f32 * 0.37;
        let pos = Vec3::new(128.0 + 100.0 * t.cos(), 30.0 + 10.0 * (t * 0.5).sin(), 128.0 + 100.0 * t.sin());
        Camera::look_at(pos, Vec3::new(128.0, 0.0, 128.0), 60.0, 320, 240, 0.1)
    };

    let done = Arc::new(AtomicBool::new(false));
    let reader = {
        let (a, done, hf) = (activity.clone(), done.clone(), hf.clone());
        std::thread::spawn(move || {
            let mm = MinMaxPyramid::build(&hf);
            let (mut last, mut seen, mut verified) = (0u64, 0u64, 0u64);
            let start = Instant::now();
            while !(done.load(Ordering::SeqCst) && a.counter().unwrap() == last) {
                assert!(start.elapsed() < Duration::from_secs(120), "reader stalled at generation {last}");
                // `latest` checks that the header and trailer words both carry the
                // generation number: a buffer overwritten while read fails here.
                match a.latest(last).unwrap() {
                    Some(g) => {
                        assert!(g.number > last, "generation {} after {last}", g.number);
                        // Every 20th generation: the data is the one for its own camera.
                        if seen % 20 == 0 {
                            let reference = block_errors(&group_errors(&hf, &mm, &g.params), layout.m);
                            for (x, y) in g.errors.packed().iter().zip(reference.packed()) {
                                assert!(close(*x, y, 1e-5), "generation {}: GPU {x}, reference {y}", g.number);
                            }
                            verified += 1;
                        }
                        last = g.number;
                        seen += 1;
                    }
                    None => std::thread::sleep(Duration::from_micros(200)),
                }
            }
            (seen, verified, last)
        })
    };

    // The camera moves every time the previous generation is done, so that each step
    // starts one; the driver never waits on the reader.
    let start = Instant::now();
    for i in 1..=GENERATIONS {
        activity.request(ErrorParams::new(&camera_at(i), ErrorMode::Strict));
        while activity.counter().unwrap() < i {
            assert!(start.elapsed() < Duration::from_secs(120), "errors activity stalled at {i}");
            std::thread::sleep(Duration::from_micros(100));
        }
    }
    done.store(true, Ordering::SeqCst);
    let (seen, verified, last) = reader.join().expect("reader thread");
    assert_eq!(last, GENERATIONS);
    assert!(seen >= 50, "the reader saw only {seen} generations");
    assert!(verified >= 3);
    // A camera that stands still starts no new generation.
    activity.request(ErrorParams::new(&camera_at(GENERATIONS), ErrorMode::Strict));
    std::thread::sleep(Duration::from_millis(200));
    assert_eq!(activity.counter().unwrap(), GENERATIONS);
    Arc::try_unwrap(activity).ok().expect("sole owner").stop().unwrap();
    println!("{GENERATIONS} generations, reader saw {seen}, verified {verified} against the reference");
    finish(device);
}
