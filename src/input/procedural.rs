//! The built-in terrain: deterministic mountains and valleys, 2049 samples a side, so
//! the program runs with no input file.

use crate::lod::heightfield::{HeightFormat, Heightfield};

fn hash(x: i32, z: i32, seed: u32) -> f32 {
    let mut h =
        (x as u32).wrapping_mul(0x8da6_b343) ^ (z as u32).wrapping_mul(0xd816_3841) ^ seed.wrapping_mul(0xcb1a_b31f);
    h ^= h >> 13;
    h = h.wrapping_mul(0x5bd1_e995);
    h ^= h >> 15;
    (h & 0x00ff_ffff) as f32 / 16_777_215.0
}

/// Smooth value noise in [0, 1].
fn value_noise(x: f32, z: f32, seed: u32) -> f32 {
    let (x0, z0) = (x.floor(), z.floor());
    let (fx, fz) = (x - x0, z - z0);
    let (ix, iz) = (x0 as i32, z0 as i32);
    let s = |t: f32| t * t * t * (t * (t * 6.0 - 15.0) + 10.0);
    let (u, v) = (s(fx), s(fz));
    let a = hash(ix, iz, seed);
    let b = hash(ix + 1, iz, seed);
    let c = hash(ix, iz + 1, seed);
    let d = hash(ix + 1, iz + 1, seed);
    a + (b - a) * u + (c - a) * v + (a - b - c + d) * u * v
}

/// Height in metres at grid coordinates `(x, z)` of a `side`-sample terrain.
pub fn height(x: f32, z: f32, side: f32) -> f32 {
    let (px, pz) = (x / side * 9.0, z / side * 9.0);
    // Domain warp bends the ridges into valleys that wander.
    let wx = px + 0.8 * value_noise(px * 0.5, pz * 0.5, 7);
    let wz = pz + 0.8 * value_noise(px * 0.5 + 11.0, pz * 0.5, 9);
    let mut ridged = 0.0;
    let mut amp = 0.5;
    let mut freq = 1.0;
    let mut weight = 1.0f32;
    for octave in 0..9u32 {
        let n = 1.0 - (value_noise(wx * freq, wz * freq, 100 + octave) * 2.0 - 1.0).abs();
        let n = n * n * weight;
        weight = (n * 2.0).clamp(0.0, 1.0);
        ridged += n * amp;
        amp *= 0.5;
        freq *= 2.03;
    }
    let base = value_noise(px * 0.35, pz * 0.35, 3);
    // Mountains where the low-frequency base is high, rolling valleys elsewhere.
    let mountains = ridged * (0.15 + 1.4 * base * base);
    3200.0 * mountains + 150.0 * base
}

/// The built-in terrain: 2049 x 2049 samples, 30 m apart, heights in metres.
pub fn procedural() -> Heightfield {
    procedural_sized(2049)
}

/// The built-in terrain at another size (tests use small ones).
pub fn procedural_sized(side: usize) -> Heightfield {
    let samples: Vec<f32> =
        (0..side * side).map(|i| height((i % side) as f32, (i / side) as f32, side as f32)).collect();
    Heightfield::embed("built-in terrain", side, side, &samples, HeightFormat::Float32, 30.0, 1.0)
        .expect("the built-in terrain is valid")
}
