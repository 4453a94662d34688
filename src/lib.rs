//! vkterrain: a Vulkan terrain renderer after Yusuf, Mostafa and Elarif, "A
//! Multi-threaded Multi-context GPU Methodology for Real-time Terrain Rendering".
//!
//! Layout: pure logic first ([`heightfield`], [`gie`], [`quadtree`], [`audit`],
//! [`camera`]), then the thin Vulkan layer ([`vk`]) and the two activities on top of it:
//! [`errors_activity`] (the GIE pyramid, its own thread and queue) and [`blocks`] (the
//! block renderer driven by the draw thread).

pub mod audit;
pub mod bench;
pub mod block_cache;
pub mod camera;
pub mod deviation;
pub mod gie;
pub mod gpu_layout;
pub mod handoff;
pub mod heightfield;
pub mod lighting;
pub mod morph;
pub mod quadtree;
pub mod quality;
pub mod stitch;

/// SPIR-V of every shader in `glsl/`, compiled by build.rs.
pub mod shaders {
    include!(concat!(env!("OUT_DIR"), "/shaders.rs"));
}

pub mod blocks;
pub mod cli;
pub mod commands;
pub mod draw_thread;
pub mod errors_activity;
pub mod hud;
pub mod lighting_gpu;
pub mod terrain_gpu;
pub mod timeline;
pub mod trace;
pub mod viewer;
pub mod vk;
