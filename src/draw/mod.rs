//! The blocks rendering activity: the draw thread's one frame step ([`frame`]), the block
//! renderer ([`blocks`]) and the sun and sky light it shades with ([`lighting`], drawn on
//! the GPU by [`lighting_gpu`]), and which blocks are ray-cast instead of rasterized
//! ([`raycast`]).

pub mod blocks;
pub mod frame;
pub mod lighting;
pub mod lighting_gpu;
pub mod raycast;
pub mod streamed;
