//! The ONE definition of every push-constant block, uniform block and descriptor binding
//! shared by Rust and GLSL.
//!
//! `build.rs` includes this very file, writes a GLSL header (`layout.glsl` in OUT_DIR)
//! with an explicit `layout(offset = N)` on every member, and after compiling each
//! shader checks the member offsets found in the SPIR-V against the Rust offsets below.
//! A field that is misaligned for its GLSL type fails the build, so neither side can
//! drift from the other.

/// One member of a block: Rust name, GLSL type, byte offset, byte size.
#[derive(Clone, Copy, Debug)]
pub struct Field {
    pub name: &'static str,
    pub glsl: &'static str,
    pub offset: usize,
    pub size: usize,
}

/// How a block is bound in GLSL.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum BlockKind {
    PushConstant,
    Uniform { set: u32, binding: u32 },
}

/// A `#[repr(C)]` struct that also exists as a GLSL block.
pub trait GpuBlock {
    const NAME: &'static str;
    const INSTANCE: &'static str;
    const KIND: BlockKind;
    const FIELDS: &'static [Field];
    const SIZE: usize;
}

macro_rules! gpu_block {
    ($(#[$meta:meta])* $kind:ident $(($set:expr, $binding:expr))? $name:ident as $inst:ident {
        $($(#[$fmeta:meta])* $field:ident : $ty:ty => $glsl:literal,)*
    }) => {
        $(#[$meta])*
        #[repr(C)]
        #[derive(Clone, Copy, Debug, Default, PartialEq, bytemuck::Pod, bytemuck::Zeroable)]
        pub struct $name {
            $($(#[$fmeta])* pub $field: $ty,)*
        }
        impl GpuBlock for $name {
            const NAME: &'static str = stringify!($name);
            const INSTANCE: &'static str = stringify!($inst);
            const KIND: BlockKind = gpu_block!(@kind $kind $(($set, $binding))?);
            const FIELDS: &'static [Field] = &[$(Field {
                name: stringify!($field),
                glsl: $glsl,
                offset: core::mem::offset_of!($name, $field),
                size: core::mem::size_of::<$ty>(),
            },)*];
            const SIZE: usize = core::mem::size_of::<$name>();
        }
    };
    (@kind push_constant) => { BlockKind::PushConstant };
    (@kind uniform ($set:expr, $binding:expr)) => { BlockKind::Uniform { set: $set, binding: $binding } };
}

// Descriptor bindings. Every pipeline uses set 0.

/// Terrain pipeline: the heightfield (R16_UNORM or R32_SFLOAT), texelFetch only.
pub const TERRAIN_BINDING_HEIGHTS: u32 = 0;
/// Terrain pipeline: per-frame uniforms ([`FrameUniforms`]).
pub const TERRAIN_BINDING_FRAME: u32 = 1;
/// Terrain pipeline: base colour texture (a 1x1 white texel when none is given).
pub const TERRAIN_BINDING_BASE: u32 = 2;
/// Terrain pipeline: detail texture (a 1x1 white texel when none is given).
pub const TERRAIN_BINDING_DETAIL: u32 = 3;

/// Terrain pipeline: per-sample gradients and sea flags (two i16 in an R32_UINT texel).
pub const TERRAIN_BINDING_GRADIENTS: u32 = 5;

/// Terrain pipeline: sun visibility and ambient occlusion (RG8, `lighting.frag`).
pub const TERRAIN_BINDING_LIGHTING: u32 = 6;

/// Deferred shading pass (shade.frag): the depth the blocks wrote, texelFetch only.
pub const TERRAIN_BINDING_DEPTH: u32 = 7;

/// Ray-cast blocks (raycast.vert/.frag): the min/max height pyramid (RG32F, LOD L in
/// mip L-1), the errors activity's [`GIE_BINDING_MINMAX`] image, read-only.
pub const TERRAIN_BINDING_MINMAX: u32 = 8;

/// Lighting pass: the heightfield, texelFetch only.
pub const LIGHTING_BINDING_HEIGHTS: u32 = 0;

/// Vertex capture (tests): world positions written by capture.vert.
pub const CAPTURE_BINDING_POSITIONS: u32 = 4;

/// GIE pass: the heightfield.
pub const GIE_BINDING_HEIGHTS: u32 = 0;
/// GIE pass: the previous LOD's group errors (one mip of the error image).
pub const GIE_BINDING_PREV: u32 = 1;
/// GIE pass: the min/max height pyramid (RG32F, LOD L in mip L-1).
pub const GIE_BINDING_MINMAX: u32 = 2;
/// GIE pass: the exact group deviation `D_L` (R32F raw units, LOD L in mip L-1).
pub const GIE_BINDING_DEVIATION: u32 = 3;

/// Block reduction pass: the whole GIE mip chain.
pub const REDUCE_BINDING_GIE: u32 = 0;

/// Block errors over the atlas: the heightfield atlas (one tile a layer).
pub const TILE_ERRORS_BINDING_HEIGHTS: u32 = 0;
/// Block errors over the atlas: the tiles' group deviations `D` (one tile a layer).
pub const TILE_ERRORS_BINDING_DEVIATION: u32 = 1;

gpu_block! {
    /// Per-draw constants of the terrain block pipeline (paper eq. 5/6: `t` and `s`).
    push_constant BlockPush as block_pc {
        /// origin x, origin z (integer samples), stride 2^j, LOD j.
        block: [i32; 4] => "ivec4",
        /// Stride of the neighbour across each edge, or 0 when it is not coarser:
        /// x: -z (north), y: +x (east), z: +z (south), w: -x (west).
        coarser_neighbour_stride: [i32; 4] => "ivec4",
        /// Morph factor of the vertices on each edge, same order (`morph.rs`).
        morph_edges: [f32; 4] => "vec4",
        /// x: morph factor of the interior vertices; y, z, w: unused.
        morph: [f32; 4] => "vec4",
        /// Raw height of each corner: NW, NE, SE, SW (`quadtree::resolve_corners`).
        corner_raw: [f32; 4] => "vec4",
        /// Streamed frames (`HEIGHTS_ATLAS`): the tile the block is drawn from: its
        /// origin x, z (samples), its level (vertex stride 2^level) and its atlas layer.
        tile: [i32; 4] => "ivec4",
    }
}

gpu_block! {
    /// Per-frame constants of the terrain pipeline.
    uniform(0, TERRAIN_BINDING_FRAME) FrameUniforms as frame {
        view_proj: [[f32; 4]; 4] => "mat4",
        inv_view_proj: [[f32; 4]; 4] => "mat4",
        /// xyz: camera position, w: fog density.
        camera_fog: [f32; 4] => "vec4",
        /// metres at the top of the colour ramp for absolute heights (0: the ramp spans
        /// the terrain's range), height_scale, min height, max height (world units).
        terrain: [f32; 4] => "vec4",
        /// Sample spacing x, z (world units); z: terrain samples per lighting texel in
        /// streamed frames (stream.frag), unused in memory; w unused.
        spacing: [f32; 4] => "vec4",
        /// xyz: direction towards the light, w: ambient.
        light: [f32; 4] => "vec4",
        /// detail tiling factor (DTF), base weight alpha, gradient-map scale, sea level
        /// (world height at or below which level ground is water).
        texturing: [f32; 4] => "vec4",
        /// true extent in samples (x, z), grid samples along x (the shaders take the
        /// grid's size from the images), block side k.
        extent: [i32; 4] => "ivec4",
        /// heights are unorm16 (1) or float (0); y: streamed frames tinted by LOD
        /// (stream.frag: a uniform, not a pipeline of its own); unused x 2. In memory,
        /// switches that select a shading path are specialization constants
        /// (`TerrainSpec`), not flags.
        flags: [i32; 4] => "ivec4",
        /// Sky: zenith colour (rgb), w: 1 = draw the sky gradient, 0 = plain background.
        sky_zenith: [f32; 4] => "vec4",
        /// Sky: horizon colour (rgb) which is also the fog colour.
        sky_horizon: [f32; 4] => "vec4",
        /// x, y: the integer sample (x, z) that positions are relative to (SPEC 8, "Precision":
        /// 0 in memory; the camera's nearest sample for streamed frames, whose
        /// `view_proj` is relative to it), z: samples a side of an atlas layer, w: unused.
        anchor: [i32; 4] => "ivec4",
    }
}

gpu_block! {
    /// Constants of one GIE pass (Algorithm 1 for LOD `i`).
    push_constant GiePush as gie_pc {
        /// LOD i, n, unused (the mode is `SPEC_STRICT_ERRORS`), heights are unorm16 (1) or float (0).
        level: [i32; 4] => "ivec4",
        /// true extent in samples (x, z), groups per side at this LOD, unused.
        extent: [i32; 4] => "ivec4",
        /// xyz: camera position, w: kappa (pixels per unit of tangent).
        camera: [f32; 4] => "vec4",
        /// spacing x, height_scale, near, spacing z.
        params: [f32; 4] => "vec4",
    }
}

gpu_block! {
    /// Constants of one tile's block errors over the atlas (`tile_errors.frag`).
    push_constant TileErrorsPush as tile_errors_pc {
        /// atlas layer, the tile's level (its vertices are `2^level` samples apart), the
        /// heights are unorm16 (1) or float (0); w: the layer of its deviations (strict
        /// mode, `tile_errors.frag`), or how many LODs coarser than the tile the blocks
        /// shaded are (the paper's, `tile_paper.frag`).
        tile: [i32; 4] => "ivec4",
        /// the tile's first vertex in samples from the camera's anchor (x, z), the cell's
        /// first texel in the target (x, y).
        origin: [i32; 4] => "ivec4",
        /// xyz: camera position relative to the anchor, w: kappa (pixels per unit of tangent).
        camera: [f32; 4] => "vec4",
        /// spacing x, height_scale, near, spacing z.
        params: [f32; 4] => "vec4",
        /// x: quads a side of a block (`k - 1`).
        shape: [i32; 4] => "ivec4",
    }
}

gpu_block! {
    /// Constants of the sun-visibility and ambient-occlusion pass (`lighting.frag`).
    push_constant LightingPush as lighting_pc {
        /// xz: horizontal direction towards the sun in samples (unit in sample steps; see
        /// `Sun::march`), y: tangent of its
        /// elevation, w: 1 = shadows and occlusion, 0 = everything lit.
        sun: [f32; 4] => "vec4",
        /// true extent in samples (x, z), samples per lighting texel, heights are unorm16.
        grid: [i32; 4] => "ivec4",
        /// spacing x, height_scale, spacing z, metres per unit step along `sun.xz`.
        params: [f32; 4] => "vec4",
        /// x: samples per height texel (`LightingSource::stride`: 1 in memory), yzw: 0.
        source: [i32; 4] => "ivec4",
    }
}

gpu_block! {
    /// Constants of one block-error reduction pass.
    push_constant ReducePush as reduce_pc {
        /// block LOD j, GIE mip to read (j - 1), groups per block side (k - 1), unused.
        level: [i32; 4] => "ivec4",
    }
}

/// A boolean specialization constant: a switch fixed per pipeline, so that a shader
/// compiles only the branch it takes. Uniform-decided branches are not free on every
/// device: llvmpipe (lavapipe) runs both sides of such a branch under a mask, so a pixel
/// paid for every shading path and the strict errors for the paper's. The header
/// declares each one (`layout(constant_id = ID) const bool NAME = false;`) under
/// `USE_<group>`; Rust passes the same `id` to the pipeline ([`crate::vk::GraphicsPipelineDesc`]).
#[derive(Clone, Copy, Debug)]
pub struct SpecConstant {
    pub group: &'static str,
    pub name: &'static str,
    pub id: u32,
}

/// terrain.frag: normals from sixteen height fetches (`--shading heights`), not the gradient map.
pub const SPEC_NORMALS_FROM_HEIGHTS: u32 = 0;
/// terrain.frag: a base texture is bound.
pub const SPEC_BASE_TEXTURE: u32 = 1;
/// terrain.frag: a detail texture is bound.
pub const SPEC_DETAIL_TEXTURE: u32 = 2;
/// terrain.frag: tint each block by its LOD.
pub const SPEC_COLOUR_BY_LOD: u32 = 3;
/// gie.frag: strict mode (else the paper's eqs. 2-4).
pub const SPEC_STRICT_ERRORS: u32 = 4;
/// terrain.frag and stream.frag: voids are drawn as holes (`--voids hole`; flags in the
/// gradient map in memory, the atlas's second channel over tiles).
pub const SPEC_HOLES: u32 = 5;
/// stream_shade.frag and stream.frag: the gradient map holds every few samples only
/// (terrains over 2049^2), so that pixels spanning less than a held sample take the
/// surface as drawn (and forward frames each triangle's own normal).
pub const SPEC_COARSE_GRADIENTS: u32 = 6;

pub const SPEC_CONSTANTS: &[SpecConstant] = &[
    SpecConstant { group: "TerrainSpec", name: "NORMALS_FROM_HEIGHTS", id: SPEC_NORMALS_FROM_HEIGHTS },
    SpecConstant { group: "TerrainSpec", name: "BASE_TEXTURE", id: SPEC_BASE_TEXTURE },
    SpecConstant { group: "TerrainSpec", name: "DETAIL_TEXTURE", id: SPEC_DETAIL_TEXTURE },
    SpecConstant { group: "TerrainSpec", name: "COLOUR_BY_LOD", id: SPEC_COLOUR_BY_LOD },
    SpecConstant { group: "TerrainSpec", name: "HOLES", id: SPEC_HOLES },
    SpecConstant { group: "TerrainSpec", name: "COARSE_GRADIENTS", id: SPEC_COARSE_GRADIENTS },
    SpecConstant { group: "GieSpec", name: "STRICT_ERRORS", id: SPEC_STRICT_ERRORS },
];

/// The integer constants the GLSL header defines, by name.
pub const GLSL_CONSTANTS: &[(&str, u32)] = &[
    ("TERRAIN_BINDING_HEIGHTS", TERRAIN_BINDING_HEIGHTS),
    ("TERRAIN_BINDING_FRAME", TERRAIN_BINDING_FRAME),
    ("TERRAIN_BINDING_BASE", TERRAIN_BINDING_BASE),
    ("TERRAIN_BINDING_DETAIL", TERRAIN_BINDING_DETAIL),
    ("TERRAIN_BINDING_GRADIENTS", TERRAIN_BINDING_GRADIENTS),
    ("CAPTURE_BINDING_POSITIONS", CAPTURE_BINDING_POSITIONS),
    ("GIE_BINDING_HEIGHTS", GIE_BINDING_HEIGHTS),
    ("GIE_BINDING_PREV", GIE_BINDING_PREV),
    ("GIE_BINDING_MINMAX", GIE_BINDING_MINMAX),
    ("GIE_BINDING_DEVIATION", GIE_BINDING_DEVIATION),
    ("REDUCE_BINDING_GIE", REDUCE_BINDING_GIE),
    ("TILE_ERRORS_BINDING_HEIGHTS", TILE_ERRORS_BINDING_HEIGHTS),
    ("TILE_ERRORS_BINDING_DEVIATION", TILE_ERRORS_BINDING_DEVIATION),
    ("TERRAIN_BINDING_LIGHTING", TERRAIN_BINDING_LIGHTING),
    ("TERRAIN_BINDING_DEPTH", TERRAIN_BINDING_DEPTH),
    ("TERRAIN_BINDING_MINMAX", TERRAIN_BINDING_MINMAX),
    ("LIGHTING_BINDING_HEIGHTS", LIGHTING_BINDING_HEIGHTS),
    ("SUN_MAX_STEPS", SUN_MAX_STEPS),
];

/// The sun's horizon march: step `t` (in samples) grows by `max(1, t * SUN_STEP_GROWTH)`,
/// at most `SUN_MAX_STEPS` steps (reaching about 10^5 samples).
pub const SUN_MAX_STEPS: u32 = 256;
pub const SUN_STEP_GROWTH: f32 = 0.05;
/// Half-width of the penumbra, in tangent of elevation (about 1.1 degrees).
pub const SUN_SOFTNESS: f32 = 0.02;

/// Ambient occlusion: horizon directions (unit, in samples) and distances (samples).
pub const AO_DIRECTIONS: [[f32; 2]; 8] = [
    [1.0, 0.0],
    [std::f32::consts::FRAC_1_SQRT_2, std::f32::consts::FRAC_1_SQRT_2],
    [0.0, 1.0],
    [-std::f32::consts::FRAC_1_SQRT_2, std::f32::consts::FRAC_1_SQRT_2],
    [-1.0, 0.0],
    [-std::f32::consts::FRAC_1_SQRT_2, -std::f32::consts::FRAC_1_SQRT_2],
    [0.0, -1.0],
    [std::f32::consts::FRAC_1_SQRT_2, -std::f32::consts::FRAC_1_SQRT_2],
];
pub const AO_DISTANCES: [f32; 12] = [1.0, 2.0, 3.0, 4.0, 6.0, 8.0, 11.0, 16.0, 22.0, 32.0, 45.0, 64.0];

/// Colours of the LOD levels in the "colour blocks by LOD" view (level modulo 6): the
/// shader's palette and the viewer's legend.
pub const LOD_PALETTE: [[f32; 3]; 6] =
    [[1.0, 0.2, 0.2], [1.0, 0.7, 0.1], [0.9, 1.0, 0.2], [0.2, 1.0, 0.3], [0.2, 0.6, 1.0], [0.7, 0.3, 1.0]];

/// The terrain's colours where no base texture is given, for the shader and the
/// viewer's legend: colour `RAMP_COLOURS[i]` at `u = RAMP_STOPS[i]`, linear between, snow
/// blended in over `RAMP_SNOW_FROM` (on gentle slopes), water below the sea level. `u` is
/// metres above sea level over [`RAMP_TOP_M`] when heights are absolute (a georeferenced
/// DEM; snow from 3600 m), else the height's share of the terrain's own range.
pub const RAMP_STOPS: [f32; 3] = [0.0, 0.35, 0.7];
pub const RAMP_COLOURS: [[f32; 3]; 3] = [[0.10, 0.22, 0.07], [0.30, 0.27, 0.14], [0.32, 0.30, 0.28]];
pub const RAMP_SNOW: [f32; 3] = [0.85, 0.87, 0.90];
pub const RAMP_SNOW_FROM: [f32; 2] = [0.72, 0.8];
pub const RAMP_TOP_M: f32 = 5000.0;
pub const WATER_COLOUR: [f32; 3] = [0.05, 0.16, 0.30];

/// `FrameUniforms::terrain.x`, the ramp's top: [`RAMP_TOP_M`] when heights are metres
/// above sea level, else 0 (the ramp spans the terrain's own range).
pub fn ramp_top(absolute_heights: bool) -> f32 {
    if absolute_heights {
        RAMP_TOP_M
    } else {
        0.0
    }
}

/// Every block, for the header generator and the SPIR-V check.
pub fn all_blocks() -> Vec<BlockInfo> {
    vec![
        BlockInfo::of::<BlockPush>(),
        BlockInfo::of::<FrameUniforms>(),
        BlockInfo::of::<GiePush>(),
        BlockInfo::of::<ReducePush>(),
        BlockInfo::of::<TileErrorsPush>(),
        BlockInfo::of::<LightingPush>(),
    ]
}

/// A block's description as plain data.
#[derive(Clone, Debug)]
pub struct BlockInfo {
    pub name: &'static str,
    pub instance: &'static str,
    pub kind: BlockKind,
    pub fields: &'static [Field],
    pub size: usize,
}

impl BlockInfo {
    pub fn of<T: GpuBlock>() -> Self {
        BlockInfo { name: T::NAME, instance: T::INSTANCE, kind: T::KIND, fields: T::FIELDS, size: T::SIZE }
    }
}

/// Base alignment and size of a GLSL type under std140/std430 (the types used here
/// have the same rules in both).
pub fn glsl_align_size(glsl: &str) -> Option<(usize, usize)> {
    Some(match glsl {
        "float" | "int" | "uint" => (4, 4),
        "vec2" | "ivec2" | "uvec2" => (8, 8),
        "vec4" | "ivec4" | "uvec4" => (16, 16),
        "mat4" => (16, 64),
        _ => return None,
    })
}
