//! A loader test per format, with the real files in ../shared/data and generated files
//! for the formats the data set lacks.

mod common;
use common::data;
use std::path::{Path, PathBuf};
use tiff::encoder::{colortype, TiffEncoder};
use tiff::tags::Tag;
use vkterrain::input::load::{load, LoadOptions};
use vkterrain::lod::heightfield::{HeightFormat, Heightfield};

/// The loaders' scratch files live in one directory removed when the test binary's
/// last user of it drops the guard (each test holds it while it runs).
fn tmp(name: &str) -> PathBuf {
    SCRATCH.with(|d| d.path().join(name))
}

thread_local! {
    static SCRATCH: common::TempDir = common::TempDir::new("loaders");
}

fn range(hf: &Heightfield) -> (f32, f32) {
    let mut lo = f32::INFINITY;
    let mut hi = f32::NEG_INFINITY;
    let side = hf.grid()[0];
    for z in 0..hf.height {
        for x in 0..hf.width {
            let v = hf.raw[z * side + x];
            lo = lo.min(v);
            hi = hi.max(v);
        }
    }
    (lo, hi)
}

fn load_default(p: &Path) -> Heightfield {
    load(p, &LoadOptions::default()).unwrap_or_else(|e| panic!("{e}"))
}

#[test]
fn puget_sound_16bit_png() {
    let hf = load_default(&data("puget_sound/ps_height_1k.png"));
    assert_eq!((hf.width, hf.height, hf.grid(), hf.n), (1025, 1025, [1025, 1025], 10));
    assert_eq!(hf.format, HeightFormat::Unorm16);
    assert_eq!(range(&hf), (0.0, 43798.0));
    assert_eq!((hf.spacing, hf.height_scale), (160.0.into(), 0.1));
    assert_eq!(hf.raw.iter().filter(|&&v| v == 0.0).count(), 39_421);
}

#[test]
fn srtm_geotiffs_with_voids_are_filled() {
    for (name, lo, hi) in [
        ("mt_rainier_90m.tif", 263.0, 4371.0),
        ("mt_fuji_90m.tif", -16.0, 3742.0),
        ("mt_everest_90m.tif", 192.0, 8642.0),
    ] {
        let hf = load_default(&data(&format!("srtm3/{name}")));
        // 3 x 3 roots of 513: 1537^2 samples, not the 2049^2 one root would take.
        assert_eq!((hf.width, hf.height, hf.grid(), hf.roots), (1201, 1201, [1537, 1537], [3, 3]), "{name}");
        assert_eq!(hf.format, HeightFormat::Float32);
        let (a, b) = range(&hf);
        // Voids are filled from valid neighbours, so the range stays the valid range.
        assert!(a >= lo && b <= hi && a < lo + 1.0 && b > hi - 1.0, "{name}: {a}..{b}");
        assert!(!hf.raw.contains(&-32768.0));
    }
}

#[test]
fn grand_canyon_rgb_png_with_equal_channels() {
    let hf = load_default(&data("grand_canyon/gcanyon_height_4k2k.png"));
    // Two 2049^2 roots side by side: memory for 4097 x 2049 samples, not 4097^2.
    assert_eq!((hf.width, hf.height, hf.grid(), hf.roots), (4097, 2049, [4097, 2049], [2, 1]));
    assert_eq!(hf.raw.len(), 4097 * 2049);
    assert_eq!(range(&hf), (13.0, 187.0));
    assert_eq!((hf.spacing, hf.height_scale), (60.0.into(), 10.0));
    // Beyond the grid, heights clamp to its edge.
    assert_eq!(hf.raw_at(100, 4096), hf.raw_at(100, 2048));
}

#[test]
fn puget_sound_4096_jpeg_embeds_in_4097() {
    let hf = load_default(&data("puget_sound/ps_height_4k.jpg"));
    assert_eq!((hf.width, hf.height, hf.grid(), hf.n), (4096, 4096, [4097, 4097], 12));
    let (_, hi) = range(&hf);
    assert!((160.0..=180.0).contains(&hi), "max {hi}");
}

#[test]
fn generated_png_8_and_16_bit_and_colour() {
    let p8 = tmp("g8.png");
    image::GrayImage::from_fn(5, 4, |x, y| image::Luma([(x * 10 + y) as u8])).save(&p8).unwrap();
    let hf = load_default(&p8);
    assert_eq!((hf.width, hf.height, hf.raw_at(4, 3)), (5, 4, 43.0));
    let p16 = tmp("g16.png");
    image::ImageBuffer::<image::Luma<u16>, _>::from_fn(3, 3, |x, y| image::Luma([(x * 1000 + y * 30000) as u16]))
        .save(&p16)
        .unwrap();
    assert_eq!(load_default(&p16).raw_at(2, 2), 62000.0);
    let pc = tmp("colour.png");
    image::RgbImage::from_fn(4, 4, |x, _| image::Rgb([x as u8, 0, 0])).save(&pc).unwrap();
    let e = load(&pc, &LoadOptions::default()).unwrap_err().to_string();
    assert!(e.contains("colour.png") && e.contains("colour image"), "{e}");
}

#[test]
fn generated_tiffs_unsigned_signed_float_and_nodata() {
    let p = tmp("u16.tif");
    let data16: Vec<u16> = (0..12).map(|i| i * 100).collect();
    TiffEncoder::new(std::fs::File::create(&p).unwrap())
        .unwrap()
        .write_image::<colortype::Gray16>(4, 3, &data16)
        .unwrap();
    let hf = load_default(&p);
    assert_eq!((hf.format, hf.raw_at(3, 2)), (HeightFormat::Unorm16, 1100.0));

    let p = tmp("f32.tif");
    let dataf: Vec<f32> = (0..16).map(|i| i as f32 * 0.5 - 2.0).collect();
    TiffEncoder::new(std::fs::File::create(&p).unwrap())
        .unwrap()
        .write_image::<colortype::Gray32Float>(4, 4, &dataf)
        .unwrap();
    let hf = load_default(&p);
    assert_eq!((hf.format, hf.raw_at(0, 0), hf.raw_at(3, 3)), (HeightFormat::Float32, -2.0, 5.5));

    // Signed 16-bit with a GDAL_NODATA tag of -9999: the void becomes its neighbours' mean.
    let p = tmp("i16.tif");
    let mut datai: Vec<i16> = vec![10; 9];
    datai[4] = -9999;
    datai[1] = 20;
    {
        let mut enc = TiffEncoder::new(std::fs::File::create(&p).unwrap()).unwrap();
        let mut img = enc.new_image::<colortype::GrayI16>(3, 3).unwrap();
        img.encoder().write_tag(Tag::Unknown(42113), "-9999").unwrap();
        img.write_data(&datai).unwrap();
    }
    let hf = load_default(&p);
    assert_eq!(hf.raw_at(1, 1), 12.5);

    // NaN in a float TIFF that declares no NaN nodata is an error naming the sample.
    let p = tmp("nan.tif");
    let mut datan = vec![1.0f32; 9];
    datan[5] = f32::NAN;
    TiffEncoder::new(std::fs::File::create(&p).unwrap())
        .unwrap()
        .write_image::<colortype::Gray32Float>(3, 3, &datan)
        .unwrap();
    let e = load(&p, &LoadOptions::default()).unwrap_err().to_string();
    assert!(e.contains("nan.tif") && e.contains("column 2, row 1"), "{e}");
}

#[test]
fn raw_r16_and_f32_need_a_matching_size() {
    let p = tmp("h.r16");
    let v: Vec<u8> = (0..20u16).flat_map(|i| (i * 3).to_le_bytes()).collect();
    std::fs::write(&p, &v).unwrap();
    let opts = LoadOptions { raw_size: Some((5, 4)), ..Default::default() };
    let hf = load(&p, &opts).unwrap();
    assert_eq!((hf.format, hf.raw_at(4, 3)), (HeightFormat::Unorm16, 57.0));
    let e = load(&p, &LoadOptions { raw_size: Some((5, 5)), ..Default::default() }).unwrap_err().to_string();
    assert!(e.contains("h.r16") && e.contains("needs 50 bytes") && e.contains("has 40"), "{e}");
    assert!(load(&p, &LoadOptions::default()).unwrap_err().to_string().contains("--raw-size"));

    let p = tmp("h.f32");
    let v: Vec<u8> = (0..9).flat_map(|i| (i as f32 - 4.5).to_le_bytes()).collect();
    std::fs::write(&p, &v).unwrap();
    let hf = load(&p, &LoadOptions { raw_size: Some((3, 3)), ..Default::default() }).unwrap();
    assert_eq!((hf.format, hf.raw_at(2, 2)), (HeightFormat::Float32, 3.5));
}

#[test]
fn srtm_hgt_big_endian_with_voids() {
    let p = tmp("N00E000.hgt");
    let mut v = vec![0u8; 1201 * 1201 * 2];
    for i in 0..1201 * 1201 {
        let h: i16 = if i == 5000 { -32768 } else { (i % 3000) as i16 };
        v[2 * i..2 * i + 2].copy_from_slice(&h.to_be_bytes());
    }
    std::fs::write(&p, &v).unwrap();
    let hf = load_default(&p);
    assert_eq!((hf.width, hf.height, hf.grid()), (1201, 1201, [1537, 1537]));
    assert_eq!(hf.raw_at(1, 0), 1.0);
    // Placed by its name: the tile south-west of N1 E1, 3 arc-seconds a sample, on WGS 84
    // (92.8 x 92.1 m at 0.5 N).
    assert_eq!(hf.georef.crs.as_deref(), Some("EPSG:4326"));
    let d = 3.0 / 3600.0;
    assert!(
        (hf.georef.origin[0] - 0.0).abs() < 1e-9 && (hf.georef.origin[1] - 1.0).abs() < 1e-9,
        "{:?}",
        hf.georef.origin
    );
    assert!((hf.georef.step[0] - d).abs() < 1e-12 && (hf.georef.step[1] + d).abs() < 1e-12);
    assert!((hf.spacing.x - 92.77).abs() < 0.05 && (hf.spacing.z - 92.12).abs() < 0.05, "{:?}", hf.spacing);
    // A tile named nowhere is refused with the reason.
    let q = tmp("tile.hgt");
    std::fs::write(&q, &v).unwrap();
    let e = load(&q, &LoadOptions::default()).unwrap_err().to_string();
    assert!(e.contains("tile.hgt") && e.contains("N46W122.hgt"), "{e}");
    assert_ne!(hf.raw_at(5000 % 1201, 5000 / 1201), -32768.0);
    std::fs::write(&p, &v[..1000]).unwrap();
    let e = load(&p, &LoadOptions::default()).unwrap_err().to_string();
    assert!(e.contains("N00E000.hgt") && e.contains("1000 bytes"), "{e}");
}

/// The Everest tile's voids (nodata -32768) as the file has them.
fn everest_raw() -> (Vec<f32>, usize, usize) {
    let bytes = std::fs::read(data("srtm3/mt_everest_90m.tif")).unwrap();
    let mut dec = tiff::decoder::Decoder::new(std::io::Cursor::new(bytes)).unwrap();
    let (w, h) = dec.dimensions().unwrap();
    let tiff::decoder::DecodingResult::I16(v) = dec.read_image().unwrap() else { panic!("int16 expected") };
    (v.into_iter().map(|x| x as f32).collect(), w as usize, h as usize)
}

/// The 4-neighbours of sample `i` in a `w x h` grid.
fn neighbours(i: usize, w: usize, h: usize) -> impl Iterator<Item = usize> {
    let (x, z) = (i % w, i / w);
    [(x > 0).then(|| i - 1), (x + 1 < w).then(|| i + 1), (z > 0).then(|| i - w), (z + 1 < h).then(|| i + w)]
        .into_iter()
        .flatten()
}

/// Steps (absolute height differences) between 4-neighbours: `(largest and 99th
/// percentile of those touching a filled sample, largest between valid samples, 99th
/// percentile between valid samples within 5 samples of a void)`.
fn void_steps(filled: &[f32], void: &[bool], w: usize, h: usize) -> (f32, f32, f32, f32) {
    assert_eq!(filled.len(), void.len());
    // Distance (in samples, Chebyshev) to the nearest void, up to 6.
    let mut near = vec![false; void.len()];
    for (i, _) in void.iter().enumerate().filter(|(_, v)| **v) {
        let (x, z) = ((i % w) as i64, (i / w) as i64);
        for dz in -5..=5i64 {
            for dx in -5..=5i64 {
                let (nx, nz) = (x + dx, z + dz);
                if nx >= 0 && nz >= 0 && nx < w as i64 && nz < h as i64 {
                    near[(nz * w as i64 + nx) as usize] = true;
                }
            }
        }
    }
    let (mut touching, mut valid_near, mut valid_max) = (Vec::new(), Vec::new(), 0.0f32);
    for z in 0..h {
        for x in 0..w {
            let i = z * w + x;
            for j in [(x + 1 < w).then(|| i + 1), (z + 1 < h).then(|| i + w)].into_iter().flatten() {
                let step = (filled[i] - filled[j]).abs();
                if void[i] || void[j] {
                    touching.push(step);
                } else {
                    valid_max = valid_max.max(step);
                    if near[i] || near[j] {
                        valid_near.push(step);
                    }
                }
            }
        }
    }
    let p99 = |v: &mut Vec<f32>| {
        v.sort_by(f32::total_cmp);
        v[((v.len() - 1) as f64 * 0.99).round() as usize]
    };
    let largest = touching.iter().fold(0.0f32, |m, s| m.max(*s));
    (largest, p99(&mut touching), valid_max, p99(&mut valid_near))
}

/// The fill passes: at most the steepest step between valid samples, and a 99th
/// percentile at most 1.5x that of the valid steps near the voids.
fn fill_is_smooth(steps: (f32, f32, f32, f32)) -> bool {
    let (largest, p99, valid_max, valid_near_p99) = steps;
    largest <= valid_max && p99 <= 1.5 * valid_near_p99
}

/// Voids are filled with no walls: on the Everest tile (9 % void), every step that
/// touches a filled sample is no steeper than the data's steepest, and their 99th
/// percentile within 1.5x that of the real steps around the voids. The count is reported.
/// Two fills that leave walls fail the same check: fronts of nearest values meeting in
/// steps (the loader's earlier fill) and one flat value per void.
#[test]
fn voids_are_filled_without_walls() {
    let (raw, w, h) = everest_raw();
    let void: Vec<bool> = raw.iter().map(|&v| v == -32768.0).collect();
    let voids = void.iter().filter(|v| **v).count();
    assert!(voids * 20 > raw.len(), "the Everest tile should be about 9% void, is {voids} of {}", raw.len());
    let hf = load(&data("srtm3/mt_everest_90m.tif"), &LoadOptions::default()).unwrap();
    assert_eq!(hf.void_samples, voids);
    let side = hf.grid()[0];
    let filled: Vec<f32> = (0..w * h).map(|i| hf.raw[(i / w) * side + i % w]).collect();
    let steps = void_steps(&filled, &void, w, h);
    println!(
        "Laplace fill: largest {:.0}, p99 {:.0}; valid: largest {:.0}, p99 near voids {:.0}",
        steps.0, steps.1, steps.2, steps.3
    );
    assert!(fill_is_smooth(steps), "the fill leaves steps the data does not have: {steps:?}");
    for (i, &v) in raw.iter().enumerate() {
        if !void[i] {
            assert_eq!(filled[i], v, "a valid sample changed at {i}");
        }
    }

    // Mutant 1: fronts of nearest values, in waves (each void next to filled samples takes
    // their mean), with no smoothing after.
    let mut fronts = raw.clone();
    let mut done: Vec<bool> = void.iter().map(|v| !v).collect();
    loop {
        let next: Vec<(usize, f32)> = (0..fronts.len())
            .filter(|&i| !done[i])
            .filter_map(|i| {
                let known: Vec<f32> = neighbours(i, w, h).filter(|&j| done[j]).map(|j| fronts[j]).collect();
                (!known.is_empty()).then(|| (i, known.iter().sum::<f32>() / known.len() as f32))
            })
            .collect();
        if next.is_empty() {
            break;
        }
        for (i, v) in next {
            fronts[i] = v;
            done[i] = true;
        }
    }
    let s = void_steps(&fronts, &void, w, h);
    println!("fronts: largest {:.0}, p99 {:.0}", s.0, s.1);
    assert!(!fill_is_smooth(s), "the check passes fronts of nearest values: {s:?}");

    // Mutant 2: each void region one flat value (the mean of the valid samples around it).
    let mut flat = raw.clone();
    let mut seen = vec![false; raw.len()];
    for start in 0..raw.len() {
        if !void[start] || seen[start] {
            continue;
        }
        let (mut region, mut stack, mut rim) = (Vec::new(), vec![start], Vec::new());
        seen[start] = true;
        while let Some(i) = stack.pop() {
            region.push(i);
            for j in neighbours(i, w, h) {
                if !void[j] {
                    rim.push(raw[j]);
                } else if !seen[j] {
                    seen[j] = true;
                    stack.push(j);
                }
            }
        }
        let mean = rim.iter().sum::<f32>() / rim.len().max(1) as f32;
        for i in region {
            flat[i] = mean;
        }
    }
    let s = void_steps(&flat, &void, w, h);
    println!("flat per void: largest {:.0}, p99 {:.0}", s.0, s.1);
    assert!(!fill_is_smooth(s), "the check passes a flat fill per void: {s:?}");
}

/// `--voids hole`: the voids are still filled (the LOD bound needs heights) and also
/// remembered, sample by sample, to be cut out of the picture.
#[test]
fn voids_can_be_kept_as_holes() {
    let opts = LoadOptions { voids: vkterrain::input::load::VoidMode::Hole, ..LoadOptions::default() };
    let hf = load(&data("srtm3/mt_everest_90m.tif"), &opts).unwrap();
    let mask = hf.void_mask.as_ref().expect("a hole mask");
    assert_eq!(mask.len(), hf.width * hf.height);
    assert_eq!(mask.iter().filter(|&&v| v).count(), hf.void_samples);
    assert_eq!(hf.void_samples, 130_953);
    let (raw, w, _) = everest_raw();
    let i = raw.iter().position(|&v| v == -32768.0).unwrap();
    assert!(hf.is_hole((i % w) as i64, (i / w) as i64));
    assert!(hf.raw_at((i % w) as i64, (i / w) as i64) > 0.0, "filled under the hole");
    let j = raw.iter().position(|&v| v != -32768.0).unwrap();
    assert!(!hf.is_hole((j % w) as i64, (j / w) as i64));
    // The default fills and keeps no mask.
    assert!(load(&data("srtm3/mt_everest_90m.tif"), &LoadOptions::default()).unwrap().void_mask.is_none());
}
