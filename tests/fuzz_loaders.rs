//! Property tests for every heightfield loader: random bytes and randomly mutated valid
//! files never panic, and forged headers never make them allocate without bound (the
//! decoders' limits and our own size checks run before any large allocation). Bounded in
//! time: a fixed number of cases per format.

mod common;
use common::TempDir;
use proptest::prelude::*;
use std::io::Cursor;
use std::path::PathBuf;
use vkterrain::input::load::{load, LoadOptions};

fn seed(ext: &str) -> Vec<u8> {
    match ext {
        "png" => {
            let img = image::GrayImage::from_fn(9, 7, |x, y| image::Luma([(x * 20 + y) as u8]));
            let mut v = Vec::new();
            img.write_to(&mut Cursor::new(&mut v), image::ImageFormat::Png).unwrap();
            v
        }
        "jpg" => {
            let img = image::GrayImage::from_fn(16, 16, |x, y| image::Luma([(x * 9 + y * 3) as u8]));
            let mut v = Vec::new();
            img.write_to(&mut Cursor::new(&mut v), image::ImageFormat::Jpeg).unwrap();
            v
        }
        "tif" => {
            let mut v = Vec::new();
            let data: Vec<u16> = (0..35).map(|i| i * 7).collect();
            tiff::encoder::TiffEncoder::new(Cursor::new(&mut v))
                .unwrap()
                .write_image::<tiff::encoder::colortype::Gray16>(7, 5, &data)
                .unwrap();
            v
        }
        "r16" => (0..20u16).flat_map(|v| v.to_le_bytes()).collect(),
        "f32" => (0..20).flat_map(|v| (v as f32).to_le_bytes()).collect(),
        _ => unreachable!(),
    }
}

fn try_load(ext: &str, bytes: &[u8], case: u64) {
    let dir = TempDir::new("fuzz");
    let path: PathBuf = dir.path().join(format!("case{case}.{ext}"));
    std::fs::write(&path, bytes).unwrap();
    let opts = LoadOptions { raw_size: Some((5, 4)), max_grid_side: Some(4097), ..Default::default() };
    // A panic fails the property; otherwise a usable heightfield or an error naming the
    // file.
    match load(&path, &opts) {
        Ok(hf) => {
            assert!(hf.width >= 3 && hf.height >= 3, "case {case}.{ext}: {}x{}", hf.width, hf.height);
            let [gw, gh] = hf.grid();
            assert!(hf.roots[0] * hf.roots[1] <= vkterrain::lod::heightfield::max_roots(hf.width, hf.height));
            assert!(gw >= hf.width && gh >= hf.height, "{gw} x {gh} for {} x {}", hf.width, hf.height);
            assert_eq!(hf.raw.len(), gw * gh);
            assert!(hf.raw.iter().all(|v| v.is_finite()), "case {case}.{ext}: non-finite heights loaded");
        }
        Err(e) => assert!(e.to_string().contains(&format!("case{case}.{ext}")), "case {case}.{ext}: '{e}'"),
    }
}

fn mutate(mut base: Vec<u8>, edits: &[(usize, u8)], cut: Option<usize>) -> Vec<u8> {
    for &(at, v) in edits {
        if !base.is_empty() {
            let i = at % base.len();
            base[i] = v;
        }
    }
    if let Some(c) = cut {
        base.truncate(c % (base.len() + 1));
    }
    base
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 128, failure_persistence: None, ..ProptestConfig::default() })]

    #[test]
    fn mutated_files_never_panic(
        ext in prop::sample::select(vec!["png", "jpg", "tif", "r16", "f32"]),
        edits in prop::collection::vec((any::<usize>(), any::<u8>()), 0..12),
        cut in prop::option::of(any::<usize>()),
        case in any::<u64>(),
    ) {
        try_load(ext, &mutate(seed(ext), &edits, cut), case);
    }

    #[test]
    fn random_bytes_never_panic(
        ext in prop::sample::select(vec!["png", "jpg", "tif", "tiff", "r16", "f32", "hgt"]),
        bytes in prop::collection::vec(any::<u8>(), 0..512),
        case in any::<u64>(),
    ) {
        try_load(ext, &bytes, case);
    }

    /// PNG and TIFF headers that claim huge images are rejected before decoding.
    #[test]
    fn forged_dimensions_are_bounded(w in 1u32..2_000_000, h in 1u32..2_000_000, case in any::<u64>()) {
        let mut png = seed("png");
        // IHDR width and height live at bytes 16..24; the CRC no longer matches, which
        // the decoder may also report.
        png[16..20].copy_from_slice(&w.to_be_bytes());
        png[20..24].copy_from_slice(&h.to_be_bytes());
        try_load("png", &png, case);
    }
}
