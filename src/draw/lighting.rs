//! Precomputed sun shadows and ambient occlusion from the heightfield: the CPU reference
//! of `glsl/lighting.frag`, which computes the same map on the GPU at load and whenever
//! the sun moves. Per texel: how much of the sun is visible above the terrain's horizon
//! in its direction (soft over [`SUN_SOFTNESS`]), and the share of the sky seen above
//! the horizon in eight directions (1 on open flat ground).
//!
//! The shader and this file follow the same steps on the same f32 inputs (the march
//! constants and directions come from `gpu_layout`), so they agree up to the rounding of
//! a few operations; `tests/gpu_lighting.rs` compares them.

use crate::gpu::layout::{AO_DIRECTIONS, AO_DISTANCES, SUN_MAX_STEPS, SUN_SOFTNESS, SUN_STEP_GROWTH};
use crate::lod::heightfield::{Heightfield, Spacing};
use glam::Vec3;

/// The largest side of the lighting map: larger grids use one texel per 2, 4, ..
/// samples (a 4097 grid gets 2049 texels, one per two samples).
pub const MAX_LIGHTING_SIDE: usize = 2049;

/// Where the sun is: compass azimuth (degrees clockwise from north, which is -z) and
/// elevation above the horizon (degrees).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Sun {
    pub azimuth: f32,
    pub elevation: f32,
}

impl Sun {
    /// West-north-west, 54 degrees up: close to the fixed light of the first wave.
    pub const DEFAULT: Sun = Sun { azimuth: 301.0, elevation: 54.0 };

    /// Unit vector towards the sun (world: x east, y up, z south).
    pub fn direction(&self) -> Vec3 {
        let (az, el) = (self.azimuth.to_radians(), self.elevation.to_radians());
        Vec3::new(az.sin() * el.cos(), el.sin(), -az.cos() * el.cos())
    }

    /// The horizontal direction towards the sun in samples (x, z), unit in sample steps,
    /// the tangent of its elevation and the metres one such step covers, as the shader
    /// receives them. With `spacing.x != spacing.z` a world direction is a different
    /// direction in samples.
    pub fn march(&self, spacing: Spacing) -> ([f32; 2], f32, f32) {
        let az = self.azimuth.to_radians();
        let (sx, sz) = (az.sin() / spacing.x, -az.cos() / spacing.z);
        let len = (sx * sx + sz * sz).sqrt();
        ([sx / len, sz / len], self.elevation.to_radians().tan(), 1.0 / len)
    }

    /// `AZ,EL` in degrees (azimuth 0..360, elevation 0..90 exclusive), or `off`.
    pub fn parse(s: &str) -> Result<Option<Sun>, String> {
        if s.trim().eq_ignore_ascii_case("off") {
            return Ok(None);
        }
        let bad = || format!("{s}: expected AZ,EL in degrees (e.g. 301,54) or off");
        let (a, e) = s.split_once(',').ok_or_else(bad)?;
        let azimuth: f32 = a.trim().parse().map_err(|_| bad())?;
        let elevation: f32 = e.trim().parse().map_err(|_| bad())?;
        if !(0.0..=360.0).contains(&azimuth) {
            return Err(format!("{s}: azimuth {azimuth} is outside 0..360"));
        }
        if !(elevation > 0.0 && elevation < 90.0) {
            return Err(format!("{s}: elevation {elevation} must be above 0 and below 90"));
        }
        Ok(Some(Sun { azimuth, elevation }))
    }
}

/// Samples per lighting texel (a power of two) for a grid of `side` samples and a map
/// of at most `max_side` texels a side ([`MAX_LIGHTING_SIDE`] but in tests).
pub fn samples_per_texel(side: usize, max_side: usize) -> usize {
    let mut step = 1;
    while (side - 1) / step + 1 > max_side {
        step *= 2;
    }
    step
}

/// Side of the lighting map for a grid of `side` samples.
pub fn lighting_side(side: usize, max_side: usize) -> usize {
    (side - 1) / samples_per_texel(side, max_side) + 1
}

/// Texels of the lighting map along x and z for `hf`'s grid, and the samples per texel
/// (the same on both axes, chosen for the longer one).
pub fn lighting_size(hf: &Heightfield, max_side: usize) -> ([usize; 2], usize) {
    LightingSource::whole(hf).size(max_side)
}

/// The heights a lighting map is made from: `hf` holds every `stride`-th sample (a power
/// of two) of a terrain of `extent` samples, and its spacing is `stride` times the
/// terrain's. In memory that is the terrain itself (stride 1); a streamed terrain lights
/// from the tiles of a coarser level (the map has one texel per `stride` samples there),
/// and a march through the terrain's samples reads the nearest sample `hf` holds.
#[derive(Clone, Copy)]
pub struct LightingSource<'a> {
    pub hf: &'a Heightfield,
    pub stride: usize,
    pub extent: [usize; 2],
}

impl<'a> LightingSource<'a> {
    pub fn whole(hf: &'a Heightfield) -> Self {
        LightingSource { hf, stride: 1, extent: [hf.width, hf.height] }
    }

    /// `hf` holding every `stride`-th sample of a terrain of `extent` samples.
    pub fn every(hf: &'a Heightfield, stride: usize, extent: [usize; 2]) -> Self {
        debug_assert!(stride.is_power_of_two());
        debug_assert_eq!([hf.width, hf.height], extent.map(|e| (e - 1) / stride + 1));
        LightingSource { hf, stride, extent }
    }

    /// The terrain's spacing (metres between its samples).
    pub fn spacing(&self) -> Spacing {
        Spacing { x: self.hf.spacing.x / self.stride as f32, z: self.hf.spacing.z / self.stride as f32 }
    }

    /// Texels along x and z and samples per texel: `hf`'s grid taken at the terrain's
    /// resolution, as [`lighting_size`] takes an in-memory grid, with a texel only on
    /// samples `hf` holds (at least `stride` samples per texel): a texel between them
    /// would take a neighbour's height for its own and shade itself.
    pub fn size(&self, max_side: usize) -> ([usize; 2], usize) {
        let [gw, gh] = self.hf.grid().map(|g| (g - 1) * self.stride + 1);
        let step = samples_per_texel(gw.max(gh), max_side).max(self.stride);
        ([(gw - 1) / step + 1, (gh - 1) / step + 1], step)
    }

    /// World height of terrain sample `(x, z)` (not negative): the nearest sample held.
    fn height_near(&self, x: i64, z: i64) -> f32 {
        let (s, half) = (self.stride as i64, self.stride as i64 / 2);
        self.hf.height_at((x + half) / s, (z + half) / s)
    }
}

/// Sun visibility (0 shadowed .. 1 lit) and ambient occlusion (share of open sky, 1 on
/// flat open ground) at sample `(x, z)`, or `[1, 1]` without a sun.
pub fn light_at(hf: &Heightfield, x: i64, z: i64, sun: Option<Sun>) -> [f32; 2] {
    source_light_at(&LightingSource::whole(hf), x, z, sun)
}

/// [`light_at`] at terrain sample `(x, z)` of `src`.
pub fn source_light_at(src: &LightingSource, x: i64, z: i64, sun: Option<Sun>) -> [f32; 2] {
    let Some(sun) = sun else { return [1.0, 1.0] };
    let [w, h] = src.extent.map(|e| e as i64);
    let h0 = src.height_near(x, z);
    let p = [x as f32, z as f32];
    // Nearest sample to p + d t; None outside the true extent (nothing there casts).
    let at = |d: [f32; 2], t: f32| -> Option<f32> {
        let qx = (p[0] + d[0] * t + 0.5).floor() as i64;
        let qz = (p[1] + d[1] * t + 0.5).floor() as i64;
        (qx >= 0 && qz >= 0 && qx < w && qz < h).then(|| src.height_near(qx, qz))
    };
    let spacing = src.spacing();
    let (d, tan_sun, metres_per_step) = sun.march(spacing);
    let mut horizon = f32::MIN;
    let mut t = 1.0f32;
    for _ in 0..SUN_MAX_STEPS {
        let Some(hq) = at(d, t) else { break };
        horizon = horizon.max((hq - h0) / (t * metres_per_step));
        t += (t * SUN_STEP_GROWTH).max(1.0);
    }
    let visible = (0.5 + (tan_sun - horizon) / (2.0 * SUN_SOFTNESS)).clamp(0.0, 1.0);
    let mut open = 0.0;
    for d in AO_DIRECTIONS {
        let mut tan = 0.0f32;
        // Metres per unit of `t` along this direction in samples.
        let (mx, mz) = (d[0] * spacing.x, d[1] * spacing.z);
        let metres = (mx * mx + mz * mz).sqrt();
        for t in AO_DISTANCES {
            let Some(hq) = at(d, t) else { break };
            tan = tan.max((hq - h0) / (t * metres));
        }
        // 1 - sin of the horizon's elevation: the sky seen above it in this direction.
        open += 1.0 - tan / (1.0 + tan * tan).sqrt();
    }
    [visible, open / AO_DIRECTIONS.len() as f32]
}

/// The whole map, row-major, [`lighting_size`] texels: texel `(i, j)` is sample
/// `(i, j) * samples_per_texel`.
pub fn reference(hf: &Heightfield, sun: Option<Sun>, max_side: usize) -> Vec<[f32; 2]> {
    source_reference(&LightingSource::whole(hf), sun, max_side)
}

/// [`reference`] of the map made from `src`.
pub fn source_reference(src: &LightingSource, sun: Option<Sun>, max_side: usize) -> Vec<[f32; 2]> {
    let ([w, h], step) = src.size(max_side);
    let step = step as i64;
    (0..w * h).map(|i| source_light_at(src, (i % w) as i64 * step, (i / w) as i64 * step, sun)).collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::lod::heightfield::HeightFormat;

    fn field(side: usize, f: impl Fn(usize, usize) -> f32) -> Heightfield {
        crate::lod::heightfield::test_field(side, side, f)
    }

    #[test]
    fn parse_accepts_degrees_and_off_and_names_the_problem() {
        assert_eq!(Sun::parse("301,54"), Ok(Some(Sun { azimuth: 301.0, elevation: 54.0 })));
        assert_eq!(Sun::parse(" 90 , 10.5 "), Ok(Some(Sun { azimuth: 90.0, elevation: 10.5 })));
        assert_eq!(Sun::parse("off"), Ok(None));
        for bad in ["", "90", "a,b", "400,10", "90,0", "90,90", "90,-5", "NaN,10"] {
            let e = Sun::parse(bad).unwrap_err();
            assert!(e.starts_with(bad), "{bad}: {e}");
        }
    }

    #[test]
    fn directions_follow_the_compass() {
        let east = Sun { azimuth: 90.0, elevation: 30.0 }.direction();
        assert!((east - Vec3::new(30f32.to_radians().cos(), 0.5, 0.0)).length() < 1e-6, "{east}");
        let north = Sun { azimuth: 0.0, elevation: 45.0 }.direction();
        assert!(north.z < -0.7 && north.x.abs() < 1e-6, "{north}");
        // The default is the first wave's light, (-0.5, 0.8, -0.3) normalised, within 1 degree.
        let old = Vec3::new(-0.5, 0.8, -0.3).normalize();
        assert!(Sun::DEFAULT.direction().angle_between(old) < 1f32.to_radians());
    }

    #[test]
    fn map_sizes_cap_at_the_largest_side() {
        let m = MAX_LIGHTING_SIDE;
        assert_eq!((samples_per_texel(1025, m), lighting_side(1025, m)), (1, 1025));
        assert_eq!((samples_per_texel(2049, m), lighting_side(2049, m)), (1, 2049));
        assert_eq!((samples_per_texel(4097, m), lighting_side(4097, m)), (2, 2049));
        assert_eq!((samples_per_texel(16385, m), lighting_side(16385, m)), (8, 2049));
        assert_eq!((samples_per_texel(129, 65), lighting_side(129, 65)), (2, 65));
    }

    #[test]
    fn flat_ground_is_lit_and_open() {
        let hf = field(33, |_, _| 5.0);
        for sun in [Sun::DEFAULT, Sun { azimuth: 10.0, elevation: 5.0 }] {
            for l in reference(&hf, Some(sun), MAX_LIGHTING_SIDE) {
                assert_eq!(l, [1.0, 1.0]);
            }
        }
        assert!(reference(&hf, None, MAX_LIGHTING_SIDE).iter().all(|&l| l == [1.0, 1.0]));
    }

    /// A map made from every other sample marches through the terrain's samples and
    /// reads the nearest one held: on a terrain that is constant over the samples each
    /// held one stands for, it equals the map of the terrain itself, texel for texel
    /// (ridges and pits so that shadows and occlusion both vary; spacing 1.5 x 0.75 so
    /// that the halved spacing matters).
    #[test]
    fn a_map_from_every_other_sample_reads_the_nearest_one() {
        let coarse =
            |c: usize, r: usize| ((c * 7 + r * 3) % 11) as f32 * 0.8 + if c == 20 || r == 9 { 9.0 } else { 0.0 };
        let side = 65usize;
        let samples: Vec<f32> =
            (0..side * side).map(|i| coarse((i % side).div_ceil(2), (i / side).div_ceil(2))).collect();
        let full = Heightfield::embed("full", side, side, &samples, HeightFormat::Float32, [1.5, 0.75], 2.0).unwrap();
        let held: Vec<f32> = (0..33 * 33).map(|i| coarse(i % 33, i / 33)).collect();
        let half = Heightfield::embed("half", 33, 33, &held, HeightFormat::Float32, [3.0, 1.5], 2.0).unwrap();
        let src = LightingSource::every(&half, 2, [side, side]);
        assert_eq!(src.size(33), lighting_size(&full, 33));
        // Room for a texel a sample (65): still one every other sample, on the held ones
        // (a texel between two took a neighbour's height: a lattice of false shadows).
        assert_eq!(src.size(65), lighting_size(&full, 33));
        for sun in [Sun { azimuth: 70.0, elevation: 20.0 }, Sun { azimuth: 200.0, elevation: 8.0 }] {
            let want = reference(&full, Some(sun), 33);
            for max_side in [33, 65] {
                let got = source_reference(&src, Some(sun), max_side);
                assert_eq!(got, want, "{sun:?}, at most {max_side} texels a side");
            }
            assert!(want.iter().any(|l| l[0] < 0.5) && want.iter().any(|l| l[1] < 0.9), "{sun:?}: nothing shaded");
        }
    }

    /// A wall 10 high along x = 40: with the sun in the east (+x) at 30 degrees, ground
    /// west of the wall is in shadow out to 10 / tan 30 = 17.3 samples, and lit beyond;
    /// the same ground is lit with the sun in the west, and with the sun at 60 degrees
    /// the shadow is 5.8 samples long.
    #[test]
    fn a_wall_casts_a_shadow_of_the_right_length() {
        let hf = field(65, |x, _| if x == 40 { 10.0 } else { 0.0 });
        let east = Some(Sun { azimuth: 90.0, elevation: 30.0 });
        let shadow_len = 10.0 / 30f32.to_radians().tan();
        for x in 0..40i64 {
            let v = light_at(&hf, x, 32, east)[0];
            let dist = (40 - x) as f32;
            if dist < shadow_len - 1.0 {
                assert_eq!(v, 0.0, "x {x} is in the wall's shadow");
            } else if dist > shadow_len + 1.0 {
                assert_eq!(v, 1.0, "x {x} is beyond the shadow");
            }
        }
        let west = Some(Sun { azimuth: 270.0, elevation: 30.0 });
        assert_eq!(light_at(&hf, 35, 32, west)[0], 1.0);
        let high = Some(Sun { azimuth: 90.0, elevation: 60.0 });
        assert_eq!(light_at(&hf, 36, 32, high)[0], 0.0);
        assert_eq!(light_at(&hf, 30, 32, high)[0], 1.0);
        // The wall itself sees the sun.
        assert_eq!(light_at(&hf, 40, 32, east)[0], 1.0);
    }

    /// A pit is more occluded than the rim around it, which is more occluded than a
    /// peak; occlusion falls with the depth of the pit.
    #[test]
    fn occlusion_orders_pits_below_rims_below_peaks() {
        let pit = |depth: f32| {
            field(65, move |x, z| {
                let r = ((x as f32 - 32.0).powi(2) + (z as f32 - 32.0).powi(2)).sqrt();
                if r < 4.0 {
                    -depth
                } else {
                    0.0
                }
            })
        };
        let shallow = light_at(&pit(2.0), 32, 32, Some(Sun::DEFAULT))[1];
        let deep = light_at(&pit(20.0), 32, 32, Some(Sun::DEFAULT))[1];
        let rim = light_at(&pit(20.0), 32, 40, Some(Sun::DEFAULT))[1];
        assert!(deep < shallow && shallow < 1.0, "deep {deep}, shallow {shallow}");
        assert!(deep < 0.2, "a pit 20 deep and 8 wide sees little sky: {deep}");
        assert!(rim == 1.0, "ground beside a pit is open: {rim}");
        let peak = field(65, |x, z| if (x, z) == (32, 32) { 30.0 } else { 0.0 });
        assert_eq!(light_at(&peak, 32, 32, Some(Sun::DEFAULT))[1], 1.0);
        let beside = light_at(&peak, 33, 32, Some(Sun::DEFAULT))[1];
        assert!(beside < 1.0 && beside > 0.8, "one direction of eight is blocked: {beside}");
    }
}
