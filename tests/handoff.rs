//! The hand-off between the errors thread and a reader (SPEC section 4): a scripted
//! camera moving fast drives hundreds of generations while a reader thread consumes
//! them, on one shared queue, under synchronization validation: paced (one generation
//! on the GPU at a time, as on a shared queue) and free (two in flight, as on separate
//! queues).

mod common;
use common::*;
use glam::Vec3;
use std::sync::Arc;
use std::time::{Duration, Instant};
use vkterrain::errors::activity::{ErrorsActivity, Pacing};
use vkterrain::gpu::terrain::TerrainGpu;
use vkterrain::lod::block::BlockLayout;
use vkterrain::lod::camera::Camera;
use vkterrain::lod::gie::{block_errors, group_errors, ErrorMode, ErrorParams};
use vkterrain::lod::pyramid::MinMaxPyramid;
use vkterrain::trace::Trace;
use vkterrain::vk::{QueueMode, QueueRequest};

const GENERATIONS: u64 = 300;

/// Drives GENERATIONS generations, each request made once the one before has started
/// (so none is merged into the next), while a reader thread takes the newest and checks
/// it; returns the most generations seen in flight at once.
fn drive(pacing: Pacing, side: usize) -> u64 {
    let device = gpu_with(QueueRequest::Shared);
    assert_eq!(device.queue_mode, QueueMode::Shared);
    let hf = field(side, side, 2.0, |x, z| {
        ((x as f32 * 0.21).sin() * (z as f32 * 0.17).cos()) * 15.0 + ((x * z) % 7) as f32
    });
    let mm = MinMaxPyramid::build(&hf);
    let layout = BlockLayout::of(&hf, 9).unwrap();
    let terrain = Arc::new(TerrainGpu::new(&device, &hf, &mm, None, None).unwrap());
    let hf = Arc::new(hf);
    let activity =
        Arc::new(ErrorsActivity::start_with(&device, terrain, hf.clone(), layout, Trace::off(), pacing).unwrap());
    let centre = side as f32;
    let camera_at = move |i: u64| {
        // A fast flyover: a new position every step.
        let t = i as f32 * 0.37;
        let pos = Vec3::new(centre + 100.0 * t.cos(), 30.0 + 10.0 * (t * 0.5).sin(), centre + 100.0 * t.sin());
        Camera::look_at(pos, Vec3::new(centre, 0.0, centre), 60.0, 320, 240, 0.1)
    };

    let reader = {
        let (a, hf) = (activity.clone(), hf.clone());
        std::thread::spawn(move || {
            let mm = MinMaxPyramid::build(&hf);
            let (mut last, mut seen, mut verified) = (0u64, 0u64, 0u64);
            let start = Instant::now();
            while last < GENERATIONS {
                assert!(start.elapsed() < Duration::from_secs(120), "reader stalled at generation {last}");
                // `latest` checks that the header and trailer words both carry the
                // generation number: a buffer overwritten while read fails here.
                match a.latest(last).unwrap() {
                    Some(g) => {
                        assert!(g.number > last, "generation {} after {last}", g.number);
                        // Every 20th generation: the data is the one for its own camera.
                        if seen % 20 == 0 {
                            let reference = block_errors(&group_errors(&hf, &mm, &g.params), layout.m);
                            let (got, want) = (g.errors.packed(), reference.packed());
                            assert_eq!(got.len(), want.len(), "generation {}: packed lengths", g.number);
                            for (x, y) in got.iter().zip(want) {
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

    // The driver never waits on the reader, nor for a generation to finish.
    let start = Instant::now();
    for i in 1..=GENERATIONS {
        activity.request(ErrorParams::new(&camera_at(i), ErrorMode::Strict));
        while activity.started() < i {
            assert!(start.elapsed() < Duration::from_secs(120), "errors activity stalled at {i}");
            std::thread::sleep(Duration::from_micros(100));
        }
    }
    let (seen, verified, last) = reader.join().expect("reader thread");
    assert_eq!(last, GENERATIONS);
    assert!(seen >= 50, "the reader saw only {seen} generations");
    assert!(verified >= 3);
    // A camera that stands still starts no new generation: once the thread has looked
    // at the request and settled, the counter has not moved.
    activity.request(ErrorParams::new(&camera_at(GENERATIONS), ErrorMode::Strict));
    while !activity.settled() {
        assert!(start.elapsed() < Duration::from_secs(150), "errors activity never settled");
        std::thread::sleep(Duration::from_micros(100));
    }
    assert_eq!((activity.counter().unwrap(), activity.started()), (GENERATIONS, GENERATIONS));
    let most = activity.most_in_flight();
    Arc::try_unwrap(activity).ok().expect("sole owner").stop().unwrap();
    println!("{pacing:?}: {GENERATIONS} generations, reader saw {seen}, verified {verified}, {most} in flight at most");
    finish(device);
    most
}

#[test]
fn hundreds_of_generations_reach_a_concurrent_reader() {
    // Paced, as on a shared queue: a generation's first submission waits for the last
    // one before, so the GPU never has two.
    assert_eq!(drive(Pacing::Auto, 129), 1);
}

#[test]
fn two_generations_in_flight_keep_the_reader_whole() {
    // Free, as on separate queues: the next generation is submitted while the last one
    // runs, both slots written at once, while the reader copies the one before.
    assert_eq!(drive(Pacing::Free, 257), 2, "two generations were never in flight together");
}
