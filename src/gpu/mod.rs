//! What both activities share on the GPU: the heightfield image and its pyramids
//! ([`terrain`]), the one definition of push constants and bindings ([`layout`]), and the
//! SPIR-V of `glsl/` ([`shaders`]).

pub mod layout;
pub mod shaders;
pub mod terrain;
