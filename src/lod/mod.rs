//! The pure LOD core: everything the method decides on the CPU, and the references the GPU
//! passes are tested against. Plain Rust: nothing here names `ash` or `crate::vk`
//! (`tests/architecture.rs` checks it).

pub mod audit;
pub mod block;
pub mod block_cache;
pub mod camera;
pub mod deviation;
pub mod geometry;
pub mod gie;
pub mod heightfield;
pub mod mesh;
pub mod morph;
pub mod occlusion;
pub mod pyramid;
pub mod stitch;
pub mod traversal;
pub mod view;
