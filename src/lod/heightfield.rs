//! The heightfield (SPEC section 1): raw samples embedded in a `2^n + 1` grid, the true
//! extent, and a CPU height query. Files and the built-in terrain become one in
//! [`crate::input`].

use thiserror::Error;

/// Largest grid side we accept from a file header before allocating (2^15 + 1).
pub const MAX_SIDE: usize = 32769;

/// The largest world coordinate accepted (terrain extent, heights, camera): positions
/// are single precision on the GPU, and squared distances must not overflow.
pub const MAX_WORLD: f32 = 1e12;

/// Why a heightfield could not be loaded. Every message names the file.
#[derive(Debug, Error)]
pub enum HeightfieldError {
    #[error("{path}: {message}")]
    Invalid { path: String, message: String },
    #[error("{path}: {source}")]
    Io {
        path: String,
        #[source]
        source: std::io::Error,
    },
}

impl HeightfieldError {
    pub fn invalid(path: &str, message: impl Into<String>) -> Self {
        HeightfieldError::Invalid { path: path.to_string(), message: message.into() }
    }
}

/// The smallest `2^n + 1` (n >= 1) that is at least `samples`.
pub fn grid_side(samples: usize) -> usize {
    let mut n = 1;
    while (1usize << n) + 1 < samples {
        n += 1;
    }
    (1usize << n) + 1
}

/// The most square roots a grid is made of (SPEC section 1): more would save little
/// memory and cost the coarsest views one block per root. A long strip may take more
/// (see [`max_roots`]).
pub const MAX_ROOTS: usize = 16;

/// The most roots for a `width x height` input: [`MAX_ROOTS`], or for a strip longer
/// than that about two per square of its short side, so that its memory too follows its
/// size (an 8193 x 3 strip is 4096 roots of 3, not 16 roots of 1025).
pub fn max_roots(width: usize, height: usize) -> usize {
    let (long, short) = (width.max(height) - 1, width.min(height).max(2) - 1);
    MAX_ROOTS.max(2 * long.div_ceil(short))
}

/// How a `width x height` input is covered (SPEC section 1): `n` and the roots (columns,
/// rows) of a grid of `2^n + 1` squares sharing their border samples, the one that takes
/// the fewest samples with at most [`max_roots`] roots (the larger `n` on a tie). A
/// 4097 x 2049 input is two 2049^2 roots side by side (4097 x 2049 samples, not 4097^2);
/// 1201 x 1201 is 3 x 3 roots of 513 (1537^2, not 2049^2).
pub fn grid_cover(width: usize, height: usize) -> (u32, [usize; 2]) {
    let top = (grid_side(width.max(height)) - 1).trailing_zeros();
    let mut best = (top, [1, 1], usize::MAX);
    for n in (1..=top).rev() {
        let r = 1usize << n;
        let roots = [(width - 1).div_ceil(r).max(1), (height - 1).div_ceil(r).max(1)];
        if roots[0] * roots[1] > max_roots(width, height) {
            break;
        }
        let area = (roots[0] * r + 1) * (roots[1] * r + 1);
        if area < best.2 {
            best = (n, roots, area);
        }
    }
    (best.0, best.1)
}

/// How heights are stored on the GPU.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum HeightFormat {
    /// Integer samples 0..=65535 in an R16_UNORM image (16- and 8-bit inputs).
    Unorm16,
    /// Anything else (signed, float) in an R32_SFLOAT image.
    Float32,
}

/// World units between samples along each axis (SPEC section 1): `x` along image
/// columns (east for north-up data), `z` along rows (south). Different for geographic
/// inputs away from the equator and for any projected input with non-square pixels.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Spacing {
    pub x: f32,
    pub z: f32,
}

impl Spacing {
    pub fn min(self) -> f32 {
        self.x.min(self.z)
    }

    pub fn max(self) -> f32 {
        self.x.max(self.z)
    }
}

impl From<f32> for Spacing {
    fn from(s: f32) -> Self {
        Spacing { x: s, z: s }
    }
}

impl From<[f32; 2]> for Spacing {
    fn from([x, z]: [f32; 2]) -> Self {
        Spacing { x, z }
    }
}

/// What the input said about where it is (SPEC section 9), kept for messages, JSON
/// outputs and the viewer's coordinates. Plain data: the reader fills it
/// ([`crate::input::georef`]).
#[derive(Clone, Debug, Default, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct Georef {
    /// The CRS as "EPSG:4326" when it has an authority code, else its name; `None` when
    /// the file has no georeferencing.
    pub crs: Option<String>,
    /// The CRS as WKT, for coordinate transforms (empty when not georeferenced).
    pub wkt: String,
    /// CRS coordinates of sample (0, 0)'s centre.
    pub origin: [f64; 2],
    /// CRS units per sample step along x and z (signed: a north-up raster has a
    /// negative z step).
    pub step: [f64; 2],
    /// Degrees (a geographic CRS) rather than linear units.
    pub geographic: bool,
    /// Geographic inputs: the largest relative difference, anywhere in the extent,
    /// between the true metres per sample and the one spacing per axis used.
    pub worst_stretch: f64,
    /// How spacing and height scale were decided, in words, for the load message.
    pub notes: Vec<String>,
    /// Heights are metres above the vertical datum (sea level): water is at or below
    /// 0 m and colours follow absolute heights. Otherwise heights are only relative and
    /// the lowest ground is taken as the water.
    pub absolute_heights: bool,
}

/// A heightfield embedded in a grid of `roots[0] x roots[1]` squares of side `2^n + 1`
/// sharing their border samples ([`grid_cover`]).
#[derive(Clone, Debug)]
pub struct Heightfield {
    /// `n` of the roots' side `2^n + 1`.
    pub n: u32,
    /// Roots along x and z.
    pub roots: [usize; 2],
    /// Raw samples (the file's units), row-major over the grid ([`Self::grid`]): index
    /// `z * grid[0] + x`.
    pub raw: Vec<f32>,
    /// True extent in samples (columns, rows); the rest is the clamped margin.
    pub width: usize,
    pub height: usize,
    /// Metres (world units) between samples, per axis.
    pub spacing: Spacing,
    /// World units per raw unit.
    pub height_scale: f32,
    pub format: HeightFormat,
    /// Where the data came from, for messages and stats.
    pub source: String,
    /// Samples the file marked as voids (nodata), filled at load ([`crate::input::load`]).
    pub void_samples: usize,
    /// Where the file says it is.
    pub georef: Georef,
    /// `--voids hole`: which samples of the true extent (row-major, `width * height`)
    /// were voids, drawn as holes; `None` when voids are filled and drawn.
    pub void_mask: Option<Vec<bool>>,
}

impl Heightfield {
    /// Embeds `width x height` raw samples (row-major) in the smallest `2^n + 1` grid,
    /// clamping to the edge.
    pub fn embed(
        source: &str,
        width: usize,
        height: usize,
        samples: &[f32],
        format: HeightFormat,
        spacing: impl Into<Spacing>,
        height_scale: f32,
    ) -> Result<Self, HeightfieldError> {
        let spacing = spacing.into();
        if !(spacing.x.is_finite() && spacing.z.is_finite() && spacing.x > 0.0 && spacing.z > 0.0) {
            return Err(HeightfieldError::invalid(
                source,
                format!("sample spacing {} x {} is not a positive distance", spacing.x, spacing.z),
            ));
        }
        if width < 3 || height < 3 {
            return Err(HeightfieldError::invalid(
                source,
                format!("{width} x {height} is too small: a heightfield needs at least 3 x 3 samples"),
            ));
        }
        if width > MAX_SIDE || height > MAX_SIDE {
            return Err(HeightfieldError::invalid(
                source,
                format!("{width} x {height} is larger than the supported {MAX_SIDE} samples a side"),
            ));
        }
        if samples.len() != width * height {
            return Err(HeightfieldError::invalid(
                source,
                format!("expected {} samples, found {}", width * height, samples.len()),
            ));
        }
        if let Some(i) = samples.iter().position(|v| !v.is_finite()) {
            return Err(HeightfieldError::invalid(
                source,
                format!("sample at column {}, row {} is not a finite number", i % width, i / width),
            ));
        }
        let (n, roots) = grid_cover(width, height);
        let [gw, gh] = [roots[0] * (1 << n) + 1, roots[1] * (1 << n) + 1];
        let mut raw = vec![0.0f32; gw * gh];
        for z in 0..gh {
            let sz = z.min(height - 1);
            for x in 0..gw {
                raw[z * gw + x] = samples[sz * width + x.min(width - 1)];
            }
        }
        Ok(Heightfield {
            n,
            roots,
            raw,
            width,
            height,
            spacing,
            height_scale,
            format,
            source: source.to_string(),
            void_samples: 0,
            georef: Georef::default(),
            void_mask: None,
        })
    }

    /// Samples of the grid along x and z: `roots * 2^n + 1`.
    pub fn grid(&self) -> [usize; 2] {
        [self.roots[0] * (1 << self.n) + 1, self.roots[1] * (1 << self.n) + 1]
    }

    /// Cells of level `l` (`2^l` samples a side) along x and z.
    pub fn cells(&self, l: u32) -> [usize; 2] {
        [self.roots[0] << (self.n - l), self.roots[1] << (self.n - l)]
    }

    /// Raw sample at integer coordinates (clamped to the grid).
    #[inline]
    pub fn raw_at(&self, x: i64, z: i64) -> f32 {
        let [gw, gh] = self.grid();
        let x = x.clamp(0, gw as i64 - 1) as usize;
        let z = z.clamp(0, gh as i64 - 1) as usize;
        self.raw[z * gw + x]
    }

    /// World position of sample `(x, z)` with raw height `raw` (SPEC section 1), in the
    /// order the shaders compute it (`block_vertex.glsl`).
    #[inline]
    pub fn world_position(&self, x: i64, z: i64, raw: f32) -> glam::Vec3 {
        glam::Vec3::new(x as f32 * self.spacing.x, raw * self.height_scale, z as f32 * self.spacing.z)
    }

    /// World box over samples `x0..=x1`, `z0..=z1` between world heights `y[0]` and
    /// `y[1]`: the one place where sample coordinates become a box's x and z.
    #[inline]
    pub fn world_box(&self, x0: i64, z0: i64, x1: i64, z1: i64, y: [f32; 2]) -> (glam::Vec3, glam::Vec3) {
        (
            glam::Vec3::new(x0 as f32 * self.spacing.x, y[0], z0 as f32 * self.spacing.z),
            glam::Vec3::new(x1 as f32 * self.spacing.x, y[1], z1 as f32 * self.spacing.z),
        )
    }

    /// World height of a sample, computed as the shaders do (raw * scale in f32).
    #[inline]
    pub fn height_at(&self, x: i64, z: i64) -> f32 {
        self.raw_at(x, z) * self.height_scale
    }

    /// Height of the full-resolution surface the renderer draws at world `(wx, wz)`:
    /// each quad is split along the diagonal from `(x, z)` to `(x+1, z+1)`.
    pub fn surface_height(&self, wx: f32, wz: f32) -> f32 {
        let [gw, gh] = self.grid();
        let px = (wx / self.spacing.x).clamp(0.0, (gw - 1) as f32);
        let pz = (wz / self.spacing.z).clamp(0.0, (gh - 1) as f32);
        let x0 = (px.floor() as i64).min(gw as i64 - 2);
        let z0 = (pz.floor() as i64).min(gh as i64 - 2);
        let fx = px - x0 as f32;
        let fz = pz - z0 as f32;
        let h00 = self.height_at(x0, z0);
        let h10 = self.height_at(x0 + 1, z0);
        let h01 = self.height_at(x0, z0 + 1);
        let h11 = self.height_at(x0 + 1, z0 + 1);
        if fx >= fz {
            h00 + fx * (h10 - h00) + fz * (h11 - h10)
        } else {
            h00 + fz * (h01 - h00) + fx * (h11 - h01)
        }
    }

    /// World size of the true extent (x, z).
    pub fn world_extent(&self) -> (f32, f32) {
        ((self.width - 1) as f32 * self.spacing.x, (self.height - 1) as f32 * self.spacing.z)
    }

    /// World height at or below which level ground is shaded as water: 0 m when heights
    /// are metres above sea level, else the lowest height plus a thousandth of the
    /// height range (`raw_range`, raw units).
    pub fn sea_level(&self, raw_range: [f32; 2]) -> f32 {
        sea_level(self.georef.absolute_heights, raw_range.map(|h| h * self.height_scale))
    }

    /// Whether grid sample `(x, z)` is drawn as a hole (`--voids hole`): a void of the
    /// file, or a margin sample clamped to one.
    pub fn is_hole(&self, x: i64, z: i64) -> bool {
        self.void_mask.as_ref().is_some_and(|m| {
            let (x, z) = (x.clamp(0, self.width as i64 - 1) as usize, z.clamp(0, self.height as i64 - 1) as usize);
            m[z * self.width + x]
        })
    }

    /// The terrain shader's per-sample data, computed once so that a pixel fetches four
    /// texels instead of twenty heights: the gradient `(dH/dx, dH/dz)` in world units
    /// (central differences, edges clamped) as R16G16_SNORM texels, with the scale that
    /// turns `[-1, 1]` back into gradients; and two flags in the texels' lowest bits:
    /// in z, whether the sample's world height is at most `sea_level` (the water test);
    /// in x, whether it is a hole ([`Self::is_hole`]). The gradients are then rounded to
    /// even units, one unit in 32767 at most.
    pub fn gradient_map(&self, sea_level: f32) -> (Vec<[i16; 2]>, f32) {
        let [gw, gh] = self.grid().map(|v| v as i64);
        let h = |x: i64, z: i64| self.height_at(x, z);
        let (inv_x, inv_z) = (1.0 / (2.0 * self.spacing.x), 1.0 / (2.0 * self.spacing.z));
        let grads: Vec<[f32; 2]> = (0..gw * gh)
            .map(|i| {
                let (x, z) = (i % gw, i / gw);
                [(h(x + 1, z) - h(x - 1, z)) * inv_x, (h(x, z + 1) - h(x, z - 1)) * inv_z]
            })
            .collect();
        let scale = grads.iter().flatten().fold(0.0f32, |m, g| m.max(g.abs())).max(f32::MIN_POSITIVE);
        // Each texel is the nearest even integer (one unit off at most, level ground
        // exact), plus its flag; the shader clears the flag before using the gradient.
        // -32768 reads back as -1.0 like -32767, so it is never written.
        let flagged = |v: f32, flag: bool| {
            let even = (2.0 * (v / scale * 32767.0 / 2.0).round()).clamp(-32766.0, 32766.0) as i16;
            even | flag as i16
        };
        let texels = (grads.iter().enumerate())
            .map(|(i, g)| {
                let (x, z) = (i as i64 % gw, i as i64 / gw);
                [flagged(g[0], self.is_hole(x, z)), flagged(g[1], self.height_at(x, z) <= sea_level)]
            })
            .collect();
        (texels, scale)
    }

    /// Bytes of the heightfield image on the GPU.
    pub fn gpu_bytes(&self) -> usize {
        let texel = match self.format {
            HeightFormat::Unorm16 => 2,
            HeightFormat::Float32 => 4,
        };
        self.raw.len() * texel
    }
}

/// Raw samples at integer sample coordinates: the whole heightfield in memory, or the
/// tiles a streamed frame holds (`stream::draw::Resident`). The block placement, corner
/// resolution and the audit's rendered surface read samples only through this, so the
/// CPU mirror of the vertex shader is one copy for both.
pub trait RawSamples {
    fn raw_at(&self, x: i64, z: i64) -> f32;
}

impl RawSamples for Heightfield {
    #[inline]
    fn raw_at(&self, x: i64, z: i64) -> f32 {
        Heightfield::raw_at(self, x, z)
    }
}

/// A crafted float field of `w x h` samples at spacing 1, for the core's unit tests.
/// [`Heightfield::sea_level`] of a terrain whose samples span `world_range` (world
/// heights): shared with streamed terrains, which know the range without the samples.
pub fn sea_level(absolute_heights: bool, world_range: [f32; 2]) -> f32 {
    if absolute_heights {
        return 0.0;
    }
    let [lo, hi] = world_range;
    lo + 1e-3 * (hi - lo).max(1e-6)
}

#[cfg(test)]
pub(crate) fn test_field(w: usize, h: usize, f: impl Fn(usize, usize) -> f32) -> Heightfield {
    let s: Vec<f32> = (0..w * h).map(|i| f(i % w, i / w)).collect();
    Heightfield::embed("test", w, h, &s, HeightFormat::Float32, 1.0, 1.0).unwrap()
}

#[cfg(test)]
mod tests {
    use super::test_field as field;
    use super::*;

    #[test]
    fn embeds_in_the_smallest_grid_of_roots_with_clamped_margin() {
        let hf = field(5, 3, |x, z| (x + 10 * z) as f32);
        assert_eq!((hf.n, hf.roots, hf.grid()), (1, [2, 1], [5, 3]));
        assert_eq!((hf.width, hf.height), (5, 3));
        assert_eq!(hf.raw_at(4, 4), hf.raw_at(4, 2));
        let hf = field(6, 3, |x, _| x as f32);
        assert_eq!(hf.grid(), [7, 3]);
        assert_eq!(hf.raw_at(6, 0), 5.0);
        // The real data's shapes: memory follows the input's own size.
        assert_eq!(grid_cover(4097, 2049), (11, [2, 1]));
        assert_eq!(grid_cover(1201, 1201), (9, [3, 3]));
        assert_eq!(grid_cover(1025, 1025), (10, [1, 1]));
        assert_eq!(grid_cover(4096, 4096), (12, [1, 1]));
        assert_eq!(grid_cover(257, 257), (8, [1, 1]));
        // Long strips: memory follows their size too.
        assert_eq!(grid_cover(8193, 3), (1, [4096, 1]));
        assert_eq!(grid_cover(3, 8193), (1, [1, 4096]));
        let (n, roots) = grid_cover(20000, 5);
        assert!(roots[0] * roots[1] <= max_roots(20000, 5) && roots[0] << n >= 19999, "{n} {roots:?}");
        assert!(((roots[0] << n) + 1) * ((roots[1] << n) + 1) < 2 * 20000 * 5, "{n} {roots:?}");
        let hf = field(1201, 1201, |_, _| 0.0);
        assert_eq!(hf.grid(), [1537, 1537]);
    }

    #[test]
    fn rejects_tiny_and_non_finite() {
        let e = Heightfield::embed("f.r16", 2, 2, &[0.0; 4], HeightFormat::Float32, 1.0, 1.0);
        assert!(e.unwrap_err().to_string().starts_with("f.r16: 2 x 2 is too small"));
        let mut s = vec![0.0; 9];
        s[4] = f32::NAN;
        let e = Heightfield::embed("g.tif", 3, 3, &s, HeightFormat::Float32, 1.0, 1.0);
        assert!(e.unwrap_err().to_string().contains("column 1, row 1 is not a finite"));
    }

    /// The shader reads the sea flag back as `round(snorm * 32767) & 1`; check that on
    /// the texels most likely to break it (the largest gradients of either sign, where
    /// clamping meets the bit) and that the flag is exactly `height <= sea_level`.
    #[test]
    fn gradient_map_keeps_the_sea_flag_and_the_gradient() {
        // A sea-level band (rows 3 to 5) between two ridges: the largest gradients, of
        // both signs, fall on sea samples at the band's edges.
        let hf =
            field(9, 9, |x, z| if (3..=5).contains(&z) { 0.0 } else { (4.0 - (x as f32 - 4.0).abs()) * 100.0 + 50.0 });
        let sea = hf.sea_level([0.0, 450.0]);
        let (texels, scale) = hf.gradient_map(sea);
        let side = hf.grid()[0];
        let mut seen = [0; 2];
        for (i, t) in texels.iter().enumerate() {
            let (x, z) = ((i % side) as i64, (i / side) as i64);
            let as_read = |v: i16| (v as f32 / 32767.0).max(-1.0);
            let units = (as_read(t[1]) * 32767.0).round() as i32;
            let bit = units & 1 != 0;
            assert_eq!(bit, hf.height_at(x, z) <= sea, "sample ({x}, {z})");
            seen[bit as usize] += 1;
            let gx = (hf.height_at(x + 1, z) - hf.height_at(x - 1, z)) / (2.0 * hf.spacing.x);
            let gz = (hf.height_at(x, z + 1) - hf.height_at(x, z - 1)) / (2.0 * hf.spacing.z);
            let x_units = (as_read(t[0]) * 32767.0).round() as i32;
            assert_eq!(x_units & 1, 0, "no holes: the x flag is clear at ({x}, {z})");
            assert!(((x_units & !1) as f32 / 32767.0 * scale - gx).abs() <= 1.01 * scale / 32767.0, "gx at ({x}, {z})");
            let even = (units & !1) as f32 / 32767.0;
            assert!((even * scale - gz).abs() <= 1.01 * scale / 32767.0, "gz at ({x}, {z})");
            if gz == 0.0 {
                assert_eq!(even, 0.0, "level ground at ({x}, {z})");
            }
        }
        assert!(seen[0] > 0 && seen[1] > 0, "{seen:?}");
        assert!(texels.iter().any(|t| t[1] == -32765), "the negative extreme was not exercised");
        assert!(texels.iter().any(|t| t[1] == -32766), "the negative extreme was not exercised");
        assert!(texels.iter().any(|t| t[1] == 32767), "the positive extreme was not exercised");
    }

    #[test]
    fn surface_height_uses_the_a_i_diagonal() {
        // Only the far corner is raised: the a-i diagonal split puts the centre at 0.5.
        let hf = field(3, 3, |x, z| {
            if x >= 1 && z >= 1 {
                if x == 1 && z == 1 {
                    1.0
                } else {
                    0.0
                }
            } else {
                0.0
            }
        });
        assert_eq!(hf.surface_height(0.5, 0.5), 0.5);
        // On the b-h (anti-)diagonal the answer would differ: check a point off the diagonal.
        assert_eq!(hf.surface_height(0.75, 0.25), 0.25);
        assert_eq!(hf.surface_height(1.0, 1.0), 1.0);
    }
}
