//! GPU resources both activities share: the heightfield image (read-only after upload),
//! the min/max pyramid, samplers and the colour textures.

use crate::lod::heightfield::{HeightFormat, Heightfield};
use crate::lod::pyramid::MinMaxPyramid;
use crate::vk::{image_barrier, vk, Buffer, CommandPool, Device, Image, Sampler, VkResult};
use std::sync::Arc;

pub struct TerrainGpu {
    pub heights: Image,
    pub minmax: Image,
    /// Exact group deviations `D_L` (R32F, LOD L in mip L-1): strict mode's world part.
    pub deviation: Image,
    /// Per-sample gradients and sea flags for shading ([`Heightfield::gradient_map`]'s
    /// two i16 per texel, read as one R32_UINT so that one gather brings four samples).
    pub gradients: Image,
    /// The gradient map's scale and the sea level, per unit of height scale: the world
    /// values are these times the heightfield's `height_scale`, so that the viewer's
    /// vertical exaggeration (a new height scale over the same samples) keeps this image
    /// (gradients and heights scale alike, and the same samples stay at sea level).
    pub gradient_scale_per_unit: f32,
    pub sea_level_per_unit: f32,
    pub nearest: Sampler,
    pub linear: Sampler,
    pub textures: TextureImages,
    /// Raw height range (min, max) of the whole grid.
    pub raw_range: [f32; 2],
    pub bytes: u64,
}

/// An RGBA8 texture given to `TerrainGpu::new`.
pub struct Texture {
    pub width: u32,
    pub height: u32,
    pub rgba: Vec<u8>,
}

/// The base and detail textures as sampled images: each given one, or one white texel
/// (the shaders read neither then: their specialization says so).
pub struct TextureImages {
    pub base: Image,
    pub detail: Image,
    pub has_base: bool,
    pub has_detail: bool,
}

impl TextureImages {
    pub fn new(
        device: &Arc<Device>,
        pool: &CommandPool,
        base: Option<&Texture>,
        detail: Option<&Texture>,
    ) -> VkResult<TextureImages> {
        let white = Texture { width: 1, height: 1, rgba: vec![255; 4] };
        let usage = vk::ImageUsageFlags::SAMPLED | vk::ImageUsageFlags::TRANSFER_DST;
        let tex = |name: &str, t: &Texture| -> VkResult<Image> {
            let extent = vk::Extent2D { width: t.width, height: t.height };
            let img = Image::new(device, name, extent, vk::Format::R8G8B8A8_SRGB, 1, usage, false)?;
            upload(device, pool, &img, &[&t.rgba])?;
            Ok(img)
        };
        Ok(TextureImages {
            base: tex("base texture", base.unwrap_or(&white))?,
            detail: tex("detail texture", detail.unwrap_or(&white))?,
            has_base: base.is_some(),
            has_detail: detail.is_some(),
        })
    }
}

impl TerrainGpu {
    /// The gradient map's scale for `hf` (these samples at its height scale).
    pub fn gradient_scale(&self, hf: &Heightfield) -> f32 {
        self.gradient_scale_per_unit * hf.height_scale
    }

    /// World height at or below which level ground is water ([`Heightfield::sea_level`]).
    pub fn sea_level(&self, hf: &Heightfield) -> f32 {
        self.sea_level_per_unit * hf.height_scale
    }

    pub fn new(
        device: &Arc<Device>,
        hf: &Heightfield,
        mm: &MinMaxPyramid,
        base: Option<&Texture>,
        detail: Option<&Texture>,
    ) -> VkResult<Self> {
        let pool = CommandPool::new(device, device.draw_queue.family)?;
        let [gw, gh] = hf.grid().map(|v| v as u32);
        let usage = vk::ImageUsageFlags::SAMPLED | vk::ImageUsageFlags::TRANSFER_DST;
        let extent = |w: u32, h: u32| vk::Extent2D { width: w, height: h };
        let (heights, height_bytes) = heights_image(device, &pool, hf, "heightfield", true)?;

        let mips: Vec<Vec<u8>> = mm.levels.iter().map(|l| bytemuck::cast_slice(l).to_vec()).collect();
        let mip_refs: Vec<&[u8]> = mips.iter().map(|m| m.as_slice()).collect();
        // Mip l - 1 holds level l: roots << (n - l) cells along x and z.
        let [mm_w, mm_h] = hf.cells(1).map(|c| c as u32);
        let minmax =
            Image::new(device, "min/max pyramid", extent(mm_w, mm_h), vk::Format::R32G32_SFLOAT, hf.n, usage, true)?;
        upload(device, &pool, &minmax, &mip_refs)?;
        let dev_mips: Vec<&[u8]> = mm.dev.iter().map(|l| bytemuck::cast_slice(l)).collect();
        let deviation = Image::new(
            device,
            "group deviation pyramid",
            extent(mm_w, mm_h),
            vk::Format::R32_SFLOAT,
            hf.n,
            usage,
            true,
        )?;
        upload(device, &pool, &deviation, &dev_mips)?;

        let sea_level = hf.sea_level(mm.range());
        let (gradients, gradient_scale) = gradients_image(device, &pool, hf, sea_level)?;

        let textures = TextureImages::new(device, &pool, base, detail)?;
        let total = height_bytes
            + mips.iter().map(|m| m.len()).sum::<usize>()
            + mm.dev.iter().map(|l| l.len() * 4).sum::<usize>()
            + (gw * gh) as usize * 4;
        Ok(TerrainGpu {
            heights,
            minmax,
            deviation,
            gradients,
            gradient_scale_per_unit: gradient_scale / hf.height_scale,
            sea_level_per_unit: sea_level / hf.height_scale,
            nearest: Sampler::new(device, vk::Filter::NEAREST, vk::SamplerAddressMode::CLAMP_TO_EDGE)?,
            linear: Sampler::new(device, vk::Filter::LINEAR, vk::SamplerAddressMode::REPEAT)?,
            textures,
            raw_range: mm.range(),
            bytes: total as u64,
        })
    }
}

/// `hf`'s grid of raw heights as a sampled image (R16 unorm or R32 float, as the shaders
/// decode them), uploaded; `shared`: both queues read it. Also the bytes it holds.
pub fn heights_image(
    device: &Arc<Device>,
    pool: &CommandPool,
    hf: &Heightfield,
    name: &str,
    shared: bool,
) -> VkResult<(Image, usize)> {
    let [gw, gh] = hf.grid().map(|v| v as u32);
    let (format, bytes): (vk::Format, Vec<u8>) = match hf.format {
        HeightFormat::Unorm16 => {
            (vk::Format::R16_UNORM, hf.raw.iter().flat_map(|&v| (v as u16).to_le_bytes()).collect())
        }
        HeightFormat::Float32 => (vk::Format::R32_SFLOAT, bytemuck::cast_slice(&hf.raw).to_vec()),
    };
    let usage = vk::ImageUsageFlags::SAMPLED | vk::ImageUsageFlags::TRANSFER_DST;
    let image = Image::new(device, name, vk::Extent2D { width: gw, height: gh }, format, 1, usage, shared)?;
    upload(device, pool, &image, &[&bytes])?;
    Ok((image, bytes.len()))
}

/// `hf`'s gradient map ([`Heightfield::gradient_map`] with water up to `sea_level`) as
/// an R32_UINT image, one gather bringing four samples, uploaded; and its scale.
pub fn gradients_image(
    device: &Arc<Device>,
    pool: &CommandPool,
    hf: &Heightfield,
    sea_level: f32,
) -> VkResult<(Image, f32)> {
    let [gw, gh] = hf.grid().map(|v| v as u32);
    let (texels, scale) = hf.gradient_map(sea_level);
    let usage = vk::ImageUsageFlags::SAMPLED | vk::ImageUsageFlags::TRANSFER_DST;
    let extent = vk::Extent2D { width: gw, height: gh };
    let image = Image::new(device, "gradient map", extent, vk::Format::R32_UINT, 1, usage, false)?;
    upload(device, pool, &image, &[bytemuck::cast_slice(&texels)])?;
    Ok((image, scale))
}

/// Uploads every mip level of `image` and leaves it in SHADER_READ_ONLY_OPTIMAL.
pub fn upload(device: &Arc<Device>, pool: &CommandPool, image: &Image, mips: &[&[u8]]) -> VkResult<()> {
    let total: usize = mips.iter().map(|m| m.len()).sum();
    let mut staging = Buffer::new(
        device,
        "staging",
        total as u64,
        vk::BufferUsageFlags::TRANSFER_SRC,
        gpu_allocator::MemoryLocation::CpuToGpu,
    )?;
    let mut regions = Vec::new();
    {
        let dst = staging.mapped_mut()?;
        let mut at = 0usize;
        for (level, data) in mips.iter().enumerate() {
            dst[at..at + data.len()].copy_from_slice(data);
            let w = (image.extent.width >> level).max(1);
            let h = (image.extent.height >> level).max(1);
            regions.push(
                vk::BufferImageCopy::default()
                    .buffer_offset(at as u64)
                    .image_subresource(vk::ImageSubresourceLayers {
                        aspect_mask: vk::ImageAspectFlags::COLOR,
                        mip_level: level as u32,
                        base_array_layer: 0,
                        layer_count: 1,
                    })
                    .image_extent(vk::Extent3D { width: w, height: h, depth: 1 }),
            );
            at += data.len();
        }
    }
    let range = image.range(0, image.mip_levels);
    device.one_shot(pool, |cmd| {
        let undefined = (vk::PipelineStageFlags2::NONE, vk::AccessFlags2::NONE, vk::ImageLayout::UNDEFINED);
        let written =
            (vk::PipelineStageFlags2::COPY, vk::AccessFlags2::TRANSFER_WRITE, vk::ImageLayout::TRANSFER_DST_OPTIMAL);
        let sampled = (
            vk::PipelineStageFlags2::VERTEX_SHADER | vk::PipelineStageFlags2::FRAGMENT_SHADER,
            vk::AccessFlags2::SHADER_SAMPLED_READ,
            vk::ImageLayout::SHADER_READ_ONLY_OPTIMAL,
        );
        // SAFETY: `cmd` is recording; the staging buffer and image outlive the wait in
        // one_shot.
        unsafe {
            image_barrier(&device.raw, cmd, image.handle, range, undefined, written);
            device.raw.cmd_copy_buffer_to_image(
                cmd,
                staging.handle,
                image.handle,
                vk::ImageLayout::TRANSFER_DST_OPTIMAL,
                &regions,
            );
            image_barrier(&device.raw, cmd, image.handle, range, written, sampled);
        }
    })
}
