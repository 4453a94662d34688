//! The heightfield atlas of streamed frames (SPEC section 8, "Residency" and "Budgets"):
//! one array image, a tile's heights (its one-sample border included) in each layer,
//! layers handed out and reused under [`AtlasLayers`]' rules (a layer is written only
//! once every frame that drew from it has completed; a tile is drawn only once the
//! upload that wrote it has finished).
//!
//! Uploads are submitted on the draw queue and waited for here: the errors activity's
//! thread does not take them over yet, so a generation is one call of
//! [`HeightAtlas::upload`].

use crate::errors::handoff::AtlasLayers;
use crate::stream::cache::{Heights, TileData};
use crate::stream::{Grid, TileKey};
use crate::vk::{image_barrier, vk, Buffer, CommandPool, Device, Image, VkError, VkResult};
use std::sync::Arc;

/// The most layers an atlas takes, whatever the budget (llvmpipe's limit).
pub const MAX_LAYERS: u32 = 2048;

pub struct HeightAtlas {
    device: Arc<Device>,
    pool: CommandPool,
    /// Declared after the pool: dropped after it, both after the owner's wait.
    pub image: Image,
    /// Samples a side of a layer (the tile side with its border).
    pub side: u32,
    /// R16_UNORM (16-bit archives) or R32_SFLOAT.
    pub unorm16: bool,
    layers: AtlasLayers<TileKey>,
    generation: u64,
}

/// What one upload did.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct Uploaded {
    pub tiles: usize,
    pub bytes: u64,
    /// Tiles that found no layer (every one is drawn by a frame not completed yet, or
    /// kept): they wait for a later upload.
    pub waiting: usize,
}

impl HeightAtlas {
    /// Bytes of one layer: a tile with its one-sample border.
    pub fn layer_bytes(grid: &Grid) -> u64 {
        let side = (grid.tile_quads + 3) as u64;
        side * side * grid.height_bytes as u64
    }

    /// The layers an atlas of `budget_bytes` has on a device allowing `device_limit`
    /// array layers (at most [`MAX_LAYERS`]).
    pub fn layers_for(grid: &Grid, budget_bytes: u64, device_limit: u32) -> u32 {
        (budget_bytes / Self::layer_bytes(grid)).min(u64::from(device_limit.min(MAX_LAYERS))) as u32
    }

    /// An atlas for `grid`'s tiles within `budget_bytes` of device memory: as many layers
    /// as fit, at most the device's `maxImageArrayLayers` and [`MAX_LAYERS`].
    pub fn new(device: &Arc<Device>, grid: &Grid, budget_bytes: u64) -> VkResult<Self> {
        let side = (grid.tile_quads + 3) as u32;
        let unorm16 = grid.height_bytes == 2;
        let layer_bytes = Self::layer_bytes(grid);
        let layers = Self::layers_for(grid, budget_bytes, device.properties.limits.max_image_array_layers);
        if layers == 0 {
            return Err(VkError::Setup(format!(
                "--gpu-mb: {budget_bytes} bytes hold no atlas layer ({layer_bytes} bytes a tile)"
            )));
        }
        let format = if unorm16 { vk::Format::R16_UNORM } else { vk::Format::R32_SFLOAT };
        let usage =
            vk::ImageUsageFlags::SAMPLED | vk::ImageUsageFlags::TRANSFER_DST | vk::ImageUsageFlags::TRANSFER_SRC;
        let extent = vk::Extent2D { width: side, height: side };
        let image = Image::array(device, "heightfield atlas", extent, format, layers, usage, true)?;
        let pool = CommandPool::new(device, device.draw_queue.family)?;
        // Every layer starts readable (a draw's descriptor covers all of them).
        let range = image.range(0, 1);
        device.one_shot(&pool, |cmd| {
            let sampled = (
                vk::PipelineStageFlags2::VERTEX_SHADER,
                vk::AccessFlags2::SHADER_SAMPLED_READ,
                vk::ImageLayout::SHADER_READ_ONLY_OPTIMAL,
            );
            let undefined = (vk::PipelineStageFlags2::NONE, vk::AccessFlags2::NONE, vk::ImageLayout::UNDEFINED);
            // SAFETY: `cmd` is recording; the image outlives one_shot's wait.
            unsafe { image_barrier(&device.raw, cmd, image.handle, range, undefined, sampled) };
        })?;
        Ok(HeightAtlas {
            device: device.clone(),
            pool,
            image,
            side,
            unorm16,
            layers: AtlasLayers::new(layers as usize),
            generation: 0,
        })
    }

    pub fn layer_count(&self) -> u32 {
        self.image.layers
    }

    /// Is `tile` in the atlas (drawable or being written)?
    pub fn holds(&self, tile: TileKey) -> bool {
        self.layers.find(tile).is_some()
    }

    /// Writes the tiles of `tiles` the atlas does not hold into layers, as one
    /// generation, and waits for it. A resident layer is reused only when every frame
    /// that drew from it is at most `completed_frame` and `keep` does not protect its tile.
    pub fn upload(
        &mut self,
        tiles: &[&Arc<TileData>],
        completed_frame: u64,
        keep: impl Fn(TileKey) -> bool,
    ) -> VkResult<Uploaded> {
        let generation = self.generation + 1;
        let mut out = Uploaded::default();
        let mut placed = Vec::new();
        for t in tiles {
            if self.layers.find(t.key).is_some() || placed.iter().any(|(k, _): &(TileKey, usize)| *k == t.key) {
                continue;
            }
            match self.layers.claim(t.key, generation, completed_frame, &keep) {
                Some(layer) => placed.push((t.key, layer)),
                None => out.waiting += 1,
            }
        }
        if placed.is_empty() {
            return Ok(out);
        }
        let texel = if self.unorm16 { 2 } else { 4 };
        let layer_bytes = (self.side * self.side) as usize * texel;
        let mut staging = Buffer::new(
            &self.device,
            "atlas staging",
            (layer_bytes * placed.len()) as u64,
            vk::BufferUsageFlags::TRANSFER_SRC,
            gpu_allocator::MemoryLocation::CpuToGpu,
        )?;
        let mut regions = Vec::with_capacity(placed.len());
        {
            let dst = staging.mapped_mut()?;
            for (i, (key, layer)) in placed.iter().enumerate() {
                let tile = tiles.iter().find(|t| t.key == *key).expect("placed from `tiles`");
                texels(&tile.heights, self.unorm16, &mut dst[i * layer_bytes..][..layer_bytes])
                    .map_err(|e| VkError::Setup(format!("tile {key:?}: {e}")))?;
                regions.push(
                    vk::BufferImageCopy::default()
                        .buffer_offset((i * layer_bytes) as u64)
                        .image_subresource(vk::ImageSubresourceLayers {
                            aspect_mask: vk::ImageAspectFlags::COLOR,
                            mip_level: 0,
                            base_array_layer: *layer as u32,
                            layer_count: 1,
                        })
                        .image_extent(vk::Extent3D { width: self.side, height: self.side, depth: 1 }),
                );
            }
        }
        let image = &self.image;
        let layers: Vec<u32> = placed.iter().map(|(_, l)| *l as u32).collect();
        self.device.one_shot(&self.pool, |cmd| {
            // The layer's old tile is discarded; the frames that drew it have completed.
            let reused = (vk::PipelineStageFlags2::VERTEX_SHADER, vk::AccessFlags2::NONE, vk::ImageLayout::UNDEFINED);
            let written = (
                vk::PipelineStageFlags2::COPY,
                vk::AccessFlags2::TRANSFER_WRITE,
                vk::ImageLayout::TRANSFER_DST_OPTIMAL,
            );
            let sampled = (
                vk::PipelineStageFlags2::VERTEX_SHADER,
                vk::AccessFlags2::SHADER_SAMPLED_READ,
                vk::ImageLayout::SHADER_READ_ONLY_OPTIMAL,
            );
            let d = &self.device.raw;
            for &layer in &layers {
                let range = vk::ImageSubresourceRange { base_array_layer: layer, layer_count: 1, ..image.range(0, 1) };
                // SAFETY: `cmd` is recording; staging and image outlive one_shot's wait.
                unsafe { image_barrier(d, cmd, image.handle, range, reused, written) };
            }
            // SAFETY: as above; every region lies inside its layer.
            unsafe {
                d.cmd_copy_buffer_to_image(
                    cmd,
                    staging.handle,
                    image.handle,
                    vk::ImageLayout::TRANSFER_DST_OPTIMAL,
                    &regions,
                )
            };
            for &layer in &layers {
                let range = vk::ImageSubresourceRange { base_array_layer: layer, layer_count: 1, ..image.range(0, 1) };
                // SAFETY: as above.
                unsafe { image_barrier(d, cmd, image.handle, range, written, sampled) };
            }
        })?;
        self.generation = generation;
        self.layers.finish(generation);
        out.tiles = placed.len();
        out.bytes = (layer_bytes * placed.len()) as u64;
        Ok(out)
    }

    /// The layer frame `frame` draws `tile` from (recorded: the layer is kept until that
    /// frame completes); `None` when it is not resident.
    pub fn draw_layer(&mut self, tile: TileKey, frame: u64) -> Option<u32> {
        self.layers.draw(tile, frame).map(|l| l as u32)
    }
}

/// A tile's heights as the atlas's texels: 16-bit integers for R16_UNORM (exact: the
/// shader rounds `texel * 65535` back), f32 otherwise.
pub fn texels(heights: &Heights, unorm16: bool, dst: &mut [u8]) -> Result<(), String> {
    let n = dst.len() / if unorm16 { 2 } else { 4 };
    let count = match heights {
        Heights::Unorm16(v) => v.len(),
        Heights::Float32(v) => v.len(),
    };
    if count != n {
        return Err(format!("{count} heights for a layer of {n}"));
    }
    for i in 0..n {
        let h = heights.get(i);
        if unorm16 {
            if h.fract() != 0.0 || !(0.0..=65535.0).contains(&h) {
                return Err(format!("height {h} in a 16-bit archive"));
            }
            dst[2 * i..2 * i + 2].copy_from_slice(&(h as u16).to_ne_bytes());
        } else {
            dst[4 * i..4 * i + 4].copy_from_slice(&h.to_ne_bytes());
        }
    }
    Ok(())
}
