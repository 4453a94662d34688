//! One tile's payload (SPEC section 8): the LOD-`t` vertices of its square with a
//! one-vertex border, and the camera-independent part of the bound for its own level,
//! `D_t` of each of its LOD-`t` groups; in a tile with voids drawn as holes (`prepare
//! --voids hole`), which of its vertices are voids. Little-endian, versioned, with a
//! CRC-32 of the body; the container compresses each payload.

/// Payload layout version of a tile without a void mask (every tile before masks).
pub const TILE_VERSION: u16 = 1;
/// Layout version of a tile with a void mask: version 1's body, then one bit a vertex.
pub const TILE_VERSION_VOIDS: u16 = 2;
const MAGIC: &[u8; 4] = b"VKTT";
const HEAD: usize = 24;

/// Heights as stored: the GPU formats of [`crate::lod::heightfield::HeightFormat`].
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Samples {
    Unorm16 = 0,
    Float32 = 1,
}

/// A decoded tile: `side x side` heights (raw units, row-major, the border included:
/// vertex `(i, j)` of the tile's square is at `(i + 1, j + 1)`), and `D_t` of its
/// `T x T` groups, row-major (empty at level 0, where `D_0 = 0`); the top tile then
/// holds `D` of every coarser level too, `D_{t+1}` (`T/2` a side) and so on up to the
/// one group of LOD `n`.
#[derive(Clone, Debug, PartialEq)]
pub struct Tile {
    pub level: u8,
    pub tx: u32,
    pub tz: u32,
    pub side: usize,
    pub heights: Vec<f32>,
    pub deviation: Vec<f32>,
    /// Which of the `side x side` vertices are voids (row-major, the border included),
    /// where the tile has any and its archive keeps them; `None` otherwise.
    pub voids: Option<Vec<bool>>,
}

impl Tile {
    /// Vertices a side of the tile's square (no border).
    pub fn vertices(&self) -> usize {
        self.side - 2
    }
}

/// Bytes of a payload with `side^2` heights and `deviations` values of `D`, and a void
/// mask if `voids`.
pub fn payload_len(samples: Samples, side: usize, deviations: usize, voids: bool) -> usize {
    HEAD + side * side * sample_bytes(samples) + deviations * 4 + if voids { mask_bytes(side) } else { 0 }
}

/// Bytes of a void mask: one bit a vertex, the lowest bit first.
fn mask_bytes(side: usize) -> usize {
    (side * side).div_ceil(8)
}

fn sample_bytes(samples: Samples) -> usize {
    match samples {
        Samples::Unorm16 => 2,
        Samples::Float32 => 4,
    }
}

pub fn encode(tile: &Tile, samples: Samples) -> Vec<u8> {
    let n = tile.side * tile.side;
    assert_eq!(tile.heights.len(), n, "tile heights");
    let mut body = Vec::with_capacity(n * 4 + tile.deviation.len() * 4);
    // Row-wise differences: neighbouring heights are close, so gzip finds small numbers.
    for row in tile.heights.chunks(tile.side) {
        let mut prev = 0u32;
        for &h in row {
            let v = match samples {
                Samples::Unorm16 => h as u32,
                Samples::Float32 => h.to_bits(),
            };
            let d = v.wrapping_sub(prev);
            prev = v;
            match samples {
                Samples::Unorm16 => body.extend_from_slice(&(d as u16).to_le_bytes()),
                Samples::Float32 => body.extend_from_slice(&d.to_le_bytes()),
            }
        }
    }
    for d in &tile.deviation {
        body.extend_from_slice(&d.to_le_bytes());
    }
    if let Some(voids) = &tile.voids {
        assert_eq!(voids.len(), n, "tile voids");
        let mut mask = vec![0u8; mask_bytes(tile.side)];
        for (i, _) in voids.iter().enumerate().filter(|(_, v)| **v) {
            mask[i / 8] |= 1 << (i % 8);
        }
        body.extend_from_slice(&mask);
    }
    let version = if tile.voids.is_some() { TILE_VERSION_VOIDS } else { TILE_VERSION };
    let mut out = Vec::with_capacity(HEAD + body.len());
    out.extend_from_slice(MAGIC);
    out.extend_from_slice(&version.to_le_bytes());
    out.push(samples as u8);
    out.push(tile.level);
    out.extend_from_slice(&tile.tx.to_le_bytes());
    out.extend_from_slice(&tile.tz.to_le_bytes());
    out.extend_from_slice(&(tile.side as u32).to_le_bytes());
    out.extend_from_slice(&crc32fast::hash(&body).to_le_bytes());
    out.extend_from_slice(&body);
    out
}

/// Decodes a payload that should be tile `(level, tx, tz)` with `side` vertices a side
/// and `deviations` values of `D`; the error says what is wrong, the caller names the
/// tile.
pub fn decode(
    payload: &[u8],
    samples: Samples,
    level: u8,
    tx: u32,
    tz: u32,
    side: usize,
    deviations: usize,
) -> Result<Tile, String> {
    if payload.len() < HEAD {
        return Err(format!("payload of {} bytes is shorter than a tile header", payload.len()));
    }
    if &payload[..4] != MAGIC {
        return Err("payload is not a vkterrain tile (bad magic)".into());
    }
    let u32_at = |i: usize| u32::from_le_bytes(payload[i..i + 4].try_into().expect("4 bytes"));
    let version = u16::from_le_bytes([payload[4], payload[5]]);
    if version != TILE_VERSION && version != TILE_VERSION_VOIDS {
        return Err(format!(
            "tile layout version {version} (this build reads {TILE_VERSION} and {TILE_VERSION_VOIDS})"
        ));
    }
    let has_voids = version == TILE_VERSION_VOIDS;
    let got = (payload[7], u32_at(8), u32_at(12));
    if got != (level, tx, tz) {
        return Err(format!(
            "payload is tile level {} ({}, {}), not the one the directory points at",
            got.0, got.1, got.2
        ));
    }
    if payload[6] != samples as u8 || u32_at(16) as usize != side {
        return Err(format!("sample format {} / side {} differ from the archive's", payload[6], u32_at(16)));
    }
    let body = &payload[HEAD..];
    if crc32fast::hash(body) != u32_at(20) {
        return Err("checksum mismatch (the tile's data is corrupt)".into());
    }
    let width = sample_bytes(samples);
    let expected = payload_len(samples, side, deviations, has_voids) - HEAD;
    if body.len() != expected {
        return Err(format!("body of {} bytes, expected {expected}", body.len()));
    }
    let (hb, rest) = body.split_at(side * side * width);
    let (db, mb) = rest.split_at(deviations * 4);
    let mut heights = Vec::with_capacity(side * side);
    for row in hb.chunks(side * width) {
        let mut prev = 0u32;
        for v in row.chunks(width) {
            let d = match samples {
                Samples::Unorm16 => u16::from_le_bytes([v[0], v[1]]) as u32,
                Samples::Float32 => u32::from_le_bytes(v.try_into().expect("4 bytes")),
            };
            prev = match samples {
                Samples::Unorm16 => (prev as u16).wrapping_add(d as u16) as u32,
                Samples::Float32 => prev.wrapping_add(d),
            };
            heights.push(match samples {
                Samples::Unorm16 => prev as f32,
                Samples::Float32 => f32::from_bits(prev),
            });
        }
    }
    let deviation = db.chunks(4).map(|v| f32::from_le_bytes(v.try_into().expect("4 bytes"))).collect();
    let voids = has_voids.then(|| (0..side * side).map(|i| mb[i / 8] & (1 << (i % 8)) != 0).collect());
    Ok(Tile { level, tx, tz, side, heights, deviation, voids })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn sample(level: u8, samples: Samples) -> Tile {
        let side = 11;
        let heights = (0..side * side)
            .map(|i| match samples {
                Samples::Unorm16 => ((i * 7919) % 65536) as f32,
                Samples::Float32 => (i as f32 * 0.37).sin() * 1e4 - 3.25,
            })
            .collect();
        let deviation = if level == 0 { vec![] } else { (0..64).map(|i| i as f32 * 0.125).collect() };
        Tile { level, tx: 3, tz: 9, side, heights, deviation, voids: None }
    }

    #[test]
    fn tiles_round_trip_in_both_formats() {
        for samples in [Samples::Unorm16, Samples::Float32] {
            for level in [0u8, 2] {
                let t = sample(level, samples);
                let bytes = encode(&t, samples);
                assert_eq!(decode(&bytes, samples, level, 3, 9, 11, if level == 0 { 0 } else { 64 }).unwrap(), t);
            }
        }
    }

    /// A mask of 121 bits (not a whole number of bytes) with a void at each end and
    /// one inside comes back bit for bit; a tile without one stays version 1.
    #[test]
    fn a_void_mask_round_trips_and_only_a_tile_with_one_changes_version() {
        let plain = sample(2, Samples::Unorm16);
        assert_eq!(u16::from_le_bytes([encode(&plain, Samples::Unorm16)[4], encode(&plain, Samples::Unorm16)[5]]), 1);
        let mut t = plain;
        t.voids = Some((0..121).map(|i| i == 0 || i == 120 || i == 37).collect());
        let bytes = encode(&t, Samples::Unorm16);
        assert_eq!(u16::from_le_bytes([bytes[4], bytes[5]]), TILE_VERSION_VOIDS);
        let back = decode(&bytes, Samples::Unorm16, 2, 3, 9, 11, 64).unwrap();
        assert_eq!(back, t);
        for i in 0..bytes.len() {
            let mut bad = bytes.clone();
            bad[i] ^= 0x04;
            assert!(decode(&bad, Samples::Unorm16, 2, 3, 9, 11, 64).is_err(), "flipped byte {i} accepted");
        }
    }

    #[test]
    fn every_corrupt_byte_and_every_mismatch_is_refused() {
        let t = sample(1, Samples::Unorm16);
        let bytes = encode(&t, Samples::Unorm16);
        for i in 0..bytes.len() {
            let mut bad = bytes.clone();
            bad[i] ^= 0x10;
            assert!(decode(&bad, Samples::Unorm16, 1, 3, 9, 11, 64).is_err(), "flipped byte {i} accepted");
        }
        assert!(decode(&bytes[..bytes.len() - 1], Samples::Unorm16, 1, 3, 9, 11, 64).is_err());
        assert!(decode(&bytes, Samples::Unorm16, 1, 3, 8, 11, 64).unwrap_err().contains("not the one"));
        assert!(decode(&bytes, Samples::Float32, 1, 3, 9, 11, 64).is_err());
    }
}
