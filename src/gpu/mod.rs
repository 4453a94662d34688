//! What both activities share on the GPU: the heightfield image and its pyramids
//! ([`terrain`]), the one definition of push constants and bindings ([`layout`]), and the
//! SPIR-V of `glsl/` ([`shaders`]); the array-image atlas streamed frames draw from
//! ([`atlas`]).

pub mod atlas;
pub mod layout;
pub mod shaders;
pub mod terrain;
