//! vkterrain: a Vulkan terrain renderer after Yusuf, Mostafa and Elarif, "A
//! Multi-threaded Multi-context GPU Methodology for Real-time Terrain Rendering".
//!
//! Layers, each using only those before it (checked by `tests/architecture.rs`):
//! - [`vk`]: a thin RAII layer over ash;
//! - [`lod`]: the pure LOD core (heightfield, pyramids, error reference, traversal,
//!   stitching, morphing, the audit), plain Rust with no Vulkan;
//! - [`input`]: where heightfields come from (file loaders, the built-in terrain);
//! - [`prepare`]: `vkterrain prepare`, a terrain of any size into a tile archive, window
//!   by window;
//! - [`stream`]: a terrain of any size streamed from its archive: the IO thread, the host
//!   cache, the traversal over resident tiles (host side, no Vulkan);
//! - [`trace`]: the Chrome trace every thread writes to;
//! - [`gpu`]: what both activities share on the GPU (the heightfield image, the layout
//!   definitions, the compiled shaders);
//! - [`errors`]: the errors activity (its thread and queue, the GIE passes, the hand-off,
//!   the feed the draw thread reads);
//! - [`draw`]: the blocks rendering activity (the one frame step, the block renderer,
//!   lighting);
//! - [`app`]: the front-ends (command line, viewer and panel, bench, quality, timeline).

pub mod app;
pub mod draw;
pub mod errors;
pub mod gpu;
pub mod input;
pub mod lod;
pub mod prepare;
pub mod stream;
pub mod trace;
pub mod vk;
