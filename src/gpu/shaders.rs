//! SPIR-V of every shader in `glsl/`, compiled by build.rs.

include!(concat!(env!("OUT_DIR"), "/shaders.rs"));
