//! The errors activity: its own CPU thread and queue rasterize the screen-space error
//! pyramid ([`activity`], its GPU work in [`passes`]), hand each finished generation over by the rules of
//! [`handoff`], and the draw thread reads them through the [`feed`]. Terrains drawn from
//! tiles have them go into the heightfield [`atlas`] under the same rules, and its
//! blocks' errors shaded over the atlas ([`atlas_passes`]).

pub mod activity;
pub mod atlas;
pub mod atlas_passes;
pub mod feed;
pub mod handoff;
pub mod passes;
