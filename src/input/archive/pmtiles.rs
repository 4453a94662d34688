//! The container: PMTiles version 3 (one file, a 127-byte header, varint directories,
//! Hilbert tile ids), written streaming and read with positioned reads. Only what the
//! terrain archive needs: gzip directories, zstd tiles, one level of leaf
//! directories. Docs: <https://github.com/protomaps/PMTiles/blob/main/spec/v3/spec.md>.

use std::io::{Read, Write};

pub const HEADER_LEN: usize = 127;
/// The header and the compressed root directory must fit in the first 16 KiB (spec 4).
pub const ROOT_LIMIT: usize = 16_384;
const MAGIC: &[u8; 7] = b"PMTiles";

/// Compression codes of the header (spec 3.3).
pub const COMPRESSION_GZIP: u8 = 2;
pub const COMPRESSION_ZSTD: u8 = 4;
/// zstd level of the tiles: level 3 is zstd's default (measured against others in
/// docs/benchmarks.md "Tile archive").
pub const TILE_ZSTD_LEVEL: i32 = 3;

pub fn zstd(raw: &[u8]) -> Vec<u8> {
    zstd::bulk::compress(raw, TILE_ZSTD_LEVEL).expect("compressing in memory")
}

/// Decompresses a tile of at most `limit` bytes (a corrupt size field must not allocate
/// without bound).
pub fn unzstd(compressed: &[u8], limit: usize) -> std::io::Result<Vec<u8>> {
    zstd::bulk::decompress(compressed, limit)
}

/// Id of tile `(z, x, y)`: tiles of all lower zooms, then the position along zoom z's
/// Hilbert curve (spec 4.1).
pub fn tile_id(z: u8, x: u32, y: u32) -> u64 {
    let n = 1u64 << z;
    let before = ((n * n) - 1) / 3;
    let (mut x, mut y) = (x as u64, y as u64);
    debug_assert!(x < n && y < n);
    let mut d = 0u64;
    let mut s = n / 2;
    while s > 0 {
        let rx = u64::from(x & s > 0);
        let ry = u64::from(y & s > 0);
        d += s * s * ((3 * rx) ^ ry);
        (x, y) = rotate(n, x, y, rx, ry);
        s /= 2;
    }
    before + d
}

fn rotate(n: u64, x: u64, y: u64, rx: u64, ry: u64) -> (u64, u64) {
    if ry == 0 {
        if rx == 1 {
            return (n - 1 - y, n - 1 - x);
        }
        return (y, x);
    }
    (x, y)
}

/// `(z, x, y)` of a tile id: the inverse of [`tile_id`].
pub fn tile_zxy(id: u64) -> (u8, u32, u32) {
    let mut z = 0u8;
    let mut before = 0u64;
    while before + (1u64 << (2 * z)) <= id {
        before += 1u64 << (2 * z);
        z += 1;
    }
    let n = 1u64 << z;
    let mut t = id - before;
    let (mut x, mut y) = (0u64, 0u64);
    let mut s = 1u64;
    while s < n {
        let rx = 1 & (t / 2);
        let ry = 1 & (t ^ rx);
        (x, y) = rotate(s, x, y, rx, ry);
        x += s * rx;
        y += s * ry;
        t /= 4;
        s *= 2;
    }
    (z, x as u32, y as u32)
}

/// The fixed header (spec 3); positions are unused by terrain (left 0).
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub struct Header {
    pub root_offset: u64,
    pub root_len: u64,
    pub metadata_offset: u64,
    pub metadata_len: u64,
    pub leaf_offset: u64,
    pub leaf_len: u64,
    pub data_offset: u64,
    pub data_len: u64,
    pub addressed_tiles: u64,
    pub tile_entries: u64,
    pub tile_contents: u64,
    pub clustered: bool,
    pub internal_compression: u8,
    pub tile_compression: u8,
    pub tile_type: u8,
    pub min_zoom: u8,
    pub max_zoom: u8,
}

impl Header {
    pub fn encode(&self) -> [u8; HEADER_LEN] {
        let mut b = [0u8; HEADER_LEN];
        b[..7].copy_from_slice(MAGIC);
        b[7] = 3;
        let words = [
            self.root_offset,
            self.root_len,
            self.metadata_offset,
            self.metadata_len,
            self.leaf_offset,
            self.leaf_len,
            self.data_offset,
            self.data_len,
            self.addressed_tiles,
            self.tile_entries,
            self.tile_contents,
        ];
        for (i, w) in words.iter().enumerate() {
            b[8 + 8 * i..16 + 8 * i].copy_from_slice(&w.to_le_bytes());
        }
        b[96] = u8::from(self.clustered);
        b[97] = self.internal_compression;
        b[98] = self.tile_compression;
        b[99] = self.tile_type;
        b[100] = self.min_zoom;
        b[101] = self.max_zoom;
        b
    }

    pub fn decode(b: &[u8]) -> Result<Self, String> {
        if b.len() < HEADER_LEN {
            return Err(format!("{} bytes, shorter than a PMTiles header ({HEADER_LEN})", b.len()));
        }
        if &b[..7] != MAGIC {
            return Err("not a PMTiles archive (no 'PMTiles' magic at the start)".into());
        }
        if b[7] != 3 {
            return Err(format!("PMTiles version {} (this build reads version 3)", b[7]));
        }
        let w = |i: usize| u64::from_le_bytes(b[8 + 8 * i..16 + 8 * i].try_into().expect("8 bytes"));
        Ok(Header {
            root_offset: w(0),
            root_len: w(1),
            metadata_offset: w(2),
            metadata_len: w(3),
            leaf_offset: w(4),
            leaf_len: w(5),
            data_offset: w(6),
            data_len: w(7),
            addressed_tiles: w(8),
            tile_entries: w(9),
            tile_contents: w(10),
            clustered: b[96] == 1,
            internal_compression: b[97],
            tile_compression: b[98],
            tile_type: b[99],
            min_zoom: b[100],
            max_zoom: b[101],
        })
    }
}

impl Header {
    /// The sections the header names (root directory, metadata, leaf directories, tile
    /// data), as `(name, offset, length)`.
    pub fn sections(&self) -> [(&'static str, u64, u64); 4] {
        [
            ("root directory", self.root_offset, self.root_len),
            ("metadata", self.metadata_offset, self.metadata_len),
            ("leaf directories", self.leaf_offset, self.leaf_len),
            ("tile data", self.data_offset, self.data_len),
        ]
    }

    /// A header that contradicts itself: a section that overflows, starts inside the
    /// header, or overlaps another. (Truncation makes none of these: a truncated archive
    /// still opens, and its missing tiles fail one by one.)
    pub fn check_sections(&self) -> Result<(), String> {
        let sections = self.sections();
        for (name, offset, len) in sections {
            if offset.checked_add(len).is_none() {
                return Err(format!("header: the {name} section at byte {offset}, {len} bytes long, overflows"));
            }
            if len > 0 && offset < HEADER_LEN as u64 {
                return Err(format!("header: the {name} section starts at byte {offset}, inside the header"));
            }
        }
        for (i, a) in sections.iter().enumerate() {
            for b in &sections[i + 1..] {
                if a.2 > 0 && b.2 > 0 && a.1 < b.1 + b.2 && b.1 < a.1 + a.2 {
                    return Err(format!(
                        "header: the {} section (bytes {}..{}) overlaps the {} section (bytes {}..{})",
                        a.0,
                        a.1,
                        a.1 + a.2,
                        b.0,
                        b.1,
                        b.1 + b.2
                    ));
                }
            }
        }
        Ok(())
    }

    /// [`Header::check_sections`], and every section (and the leaf directories' offset,
    /// even with none) within a file of `file_len` bytes: what `check` verifies.
    pub fn check_within(&self, file_len: u64) -> Result<(), String> {
        self.check_sections()?;
        for (name, offset, len) in self.sections() {
            if offset + len > file_len {
                return Err(format!(
                    "header: the {name} section (bytes {offset}..{}) lies past the end of the file ({file_len} bytes)",
                    offset + len
                ));
            }
        }
        Ok(())
    }
}

/// One directory entry (spec 4.1): `run_length` 0 points at a leaf directory.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Entry {
    pub tile_id: u64,
    pub offset: u64,
    pub length: u32,
    pub run_length: u32,
}

fn put_varint(out: &mut Vec<u8>, mut v: u64) {
    while v >= 0x80 {
        out.push((v as u8) | 0x80);
        v >>= 7;
    }
    out.push(v as u8);
}

fn get_varint(b: &[u8], at: &mut usize) -> Result<u64, String> {
    let mut v = 0u64;
    for shift in (0..64).step_by(7) {
        let byte = *b.get(*at).ok_or("directory ends inside a number")?;
        *at += 1;
        v |= u64::from(byte & 0x7f) << shift;
        if byte < 0x80 {
            return Ok(v);
        }
    }
    Err("directory number longer than 64 bits".into())
}

/// A directory, varint-encoded (spec 4.2) and gzip-compressed.
pub fn encode_directory(entries: &[Entry]) -> Vec<u8> {
    let mut raw = Vec::with_capacity(entries.len() * 8 + 8);
    put_varint(&mut raw, entries.len() as u64);
    let mut last = 0;
    for e in entries {
        put_varint(&mut raw, e.tile_id - last);
        last = e.tile_id;
    }
    for e in entries {
        put_varint(&mut raw, e.run_length.into());
    }
    for e in entries {
        put_varint(&mut raw, e.length.into());
    }
    for (i, e) in entries.iter().enumerate() {
        let contiguous = i > 0 && e.offset == entries[i - 1].offset + u64::from(entries[i - 1].length);
        put_varint(&mut raw, if contiguous { 0 } else { e.offset + 1 });
    }
    gzip(&raw, 6)
}

pub fn decode_directory(compressed: &[u8]) -> Result<Vec<Entry>, String> {
    let raw = gunzip(compressed).map_err(|e| format!("directory does not decompress: {e}"))?;
    let mut at = 0;
    let n = get_varint(&raw, &mut at)? as usize;
    if n == 0 || n > raw.len() {
        return Err(format!("directory claims {n} entries in {} bytes", raw.len()));
    }
    let mut entries = vec![Entry { tile_id: 0, offset: 0, length: 0, run_length: 0 }; n];
    let mut last = 0u64;
    for e in entries.iter_mut() {
        last = last.checked_add(get_varint(&raw, &mut at)?).ok_or("tile id overflows")?;
        e.tile_id = last;
    }
    for e in entries.iter_mut() {
        e.run_length = u32::try_from(get_varint(&raw, &mut at)?).map_err(|_| "run length too large")?;
    }
    for e in entries.iter_mut() {
        e.length = u32::try_from(get_varint(&raw, &mut at)?).map_err(|_| "entry length too large")?;
        if e.length == 0 {
            return Err("directory entry of length 0".into());
        }
    }
    for i in 0..n {
        let v = get_varint(&raw, &mut at)?;
        entries[i].offset = match v {
            0 if i > 0 => entries[i - 1].offset + u64::from(entries[i - 1].length),
            0 => return Err("first directory entry has no offset".into()),
            v => v - 1,
        };
    }
    if at != raw.len() {
        return Err(format!("{} bytes after the directory's last entry", raw.len() - at));
    }
    Ok(entries)
}

pub fn gzip(raw: &[u8], level: u32) -> Vec<u8> {
    let mut enc = flate2::write::GzEncoder::new(Vec::with_capacity(raw.len() / 2), flate2::Compression::new(level));
    enc.write_all(raw).expect("writing to memory");
    enc.finish().expect("writing to memory")
}

pub fn gunzip(compressed: &[u8]) -> std::io::Result<Vec<u8>> {
    let mut out = Vec::with_capacity(compressed.len() * 3);
    flate2::read::GzDecoder::new(compressed).read_to_end(&mut out)?;
    Ok(out)
}

/// Root directory and leaves for `entries` (sorted by tile id): all in the root when it
/// fits, else leaves of a size chosen so that the root of leaf pointers fits. Returns
/// (root, leaves section).
pub fn directories(entries: &[Entry]) -> (Vec<u8>, Vec<u8>) {
    let root = encode_directory(entries);
    if root.len() <= ROOT_LIMIT - HEADER_LEN {
        return (root, Vec::new());
    }
    let mut leaf_size = 4096usize;
    loop {
        let mut leaves = Vec::new();
        let mut pointers = Vec::new();
        for chunk in entries.chunks(leaf_size) {
            let leaf = encode_directory(chunk);
            pointers.push(Entry {
                tile_id: chunk[0].tile_id,
                offset: leaves.len() as u64,
                length: leaf.len() as u32,
                run_length: 0,
            });
            leaves.extend_from_slice(&leaf);
        }
        let root = encode_directory(&pointers);
        if root.len() <= ROOT_LIMIT - HEADER_LEN {
            return (root, leaves);
        }
        leaf_size *= 2;
    }
}

/// The entry for `id` in a sorted directory: a tile entry covering it, or the leaf
/// directory that may hold it.
pub fn find(entries: &[Entry], id: u64) -> Option<Entry> {
    let i = entries.partition_point(|e| e.tile_id <= id).checked_sub(1)?;
    let e = entries[i];
    if e.run_length == 0 || id < e.tile_id + u64::from(e.run_length) {
        Some(e)
    } else {
        None
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn tile_ids_follow_the_spec_table() {
        assert_eq!(tile_id(0, 0, 0), 0);
        assert_eq!(tile_id(1, 0, 0), 1);
        assert_eq!(tile_id(1, 0, 1), 2);
        assert_eq!(tile_id(1, 1, 1), 3);
        assert_eq!(tile_id(1, 1, 0), 4);
        assert_eq!(tile_id(2, 0, 0), 5);
        assert_eq!(tile_id(12, 3423, 1763), 19_078_479);
    }

    #[test]
    fn tile_ids_round_trip_and_are_distinct() {
        let mut seen = std::collections::HashSet::new();
        for z in 0..6u8 {
            for x in 0..1u32 << z {
                for y in 0..1u32 << z {
                    let id = tile_id(z, x, y);
                    assert_eq!(tile_zxy(id), (z, x, y));
                    assert!(seen.insert(id));
                }
            }
        }
        assert_eq!(tile_zxy(19_078_479), (12, 3423, 1763));
    }

    #[test]
    fn directories_round_trip_with_and_without_leaves() {
        for count in [1usize, 7, 100_000] {
            let entries: Vec<Entry> = (0..count as u64)
                .map(|i| Entry {
                    tile_id: i * 5 + (i % 3),
                    // Mostly contiguous, some not (the decoder's "0 = follows" rule).
                    offset: i * 1000 + if i % 7 == 0 { 17 } else { 0 },
                    length: if i % 7 == 6 { 983 } else { 1000 },
                    run_length: 1,
                })
                .collect();
            let (root, leaves) = directories(&entries);
            assert!(root.len() <= ROOT_LIMIT - HEADER_LEN);
            let root = decode_directory(&root).unwrap();
            let mut back = Vec::new();
            for p in &root {
                if p.run_length == 0 {
                    let leaf = &leaves[p.offset as usize..][..p.length as usize];
                    back.extend(decode_directory(leaf).unwrap());
                } else {
                    back.push(*p);
                }
            }
            assert_eq!(back, entries, "{count} entries");
            assert_eq!(count > 10_000, !leaves.is_empty());
        }
    }

    #[test]
    fn headers_round_trip_and_bad_ones_are_named() {
        let h = Header { root_offset: 127, root_len: 99, data_offset: 16_384, max_zoom: 5, ..Default::default() };
        assert_eq!(Header::decode(&h.encode()).unwrap(), h);
        let mut b = h.encode();
        b[7] = 2;
        assert!(Header::decode(&b).unwrap_err().contains("version 2"));
        assert!(Header::decode(b"GIF89a").unwrap_err().contains("shorter"));
        b[0] = b'X';
        assert!(Header::decode(&b).unwrap_err().contains("magic"));
    }

    #[test]
    fn find_covers_runs_and_leaves() {
        let e = |tile_id, run_length| Entry { tile_id, offset: 0, length: 1, run_length };
        let dir = [e(2, 1), e(5, 3), e(20, 0)];
        assert_eq!(find(&dir, 1), None);
        assert_eq!(find(&dir, 2), Some(dir[0]));
        assert_eq!(find(&dir, 3), None);
        assert_eq!(find(&dir, 7), Some(dir[1]));
        assert_eq!(find(&dir, 8), None);
        assert_eq!(find(&dir, 99), Some(dir[2]));
    }
}
