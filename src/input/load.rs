//! Heightfield loaders: PNG/JPEG (grayscale, or RGB with equal channels), TIFF/GeoTIFF
//! (8/16-bit, signed 16-bit, 32-bit float; tiled or striped; voids filled), raw `.r16`
//! and `.f32`, and SRTM `.hgt`.

use crate::lod::heightfield::{grid_side, HeightFormat, Heightfield, HeightfieldError, MAX_SIDE};
use std::path::Path;

/// Options shared by every subcommand that loads a heightfield.
#[derive(Clone, Debug, Default)]
pub struct LoadOptions {
    /// Metres between samples; `None` picks the format's (or the known file's) default.
    pub spacing: Option<f32>,
    /// World units per raw unit; `None` picks the default.
    pub height_scale: Option<f32>,
    /// Size of a raw `.r16`/`.f32` file.
    pub raw_size: Option<(usize, usize)>,
    /// The device's maxImageDimension2D, when known: checked before the grid is
    /// allocated.
    pub max_grid_side: Option<usize>,
}

/// Defaults for data sets we know by name (shared/data/README.md), else by sample type.
fn defaults(path: &str, bits: u32, signed_or_float: bool) -> (f32, f32) {
    let name = Path::new(path).file_name().map(|n| n.to_string_lossy().to_lowercase()).unwrap_or_default();
    if name.starts_with("ps_height_1k") {
        (160.0, 0.1)
    } else if name.starts_with("ps_height_4k") && bits == 8 {
        // The 8-bit JPEG: one unit is about 25.7 m (h16 / 257 * 0.1 m).
        (40.0, 25.7)
    } else if name.starts_with("ps_height_4k") {
        (40.0, 0.1)
    } else if name.starts_with("gcanyon") {
        (60.0, 10.0)
    } else if signed_or_float {
        (90.0, 1.0)
    } else if bits == 8 {
        (30.0, 8.0)
    } else {
        (30.0, 0.1)
    }
}

/// Loads a heightfield file; every error names the file and the problem.
pub fn load(path: &Path, opts: &LoadOptions) -> Result<Heightfield, HeightfieldError> {
    let shown = path.display().to_string();
    let meta = std::fs::metadata(path).map_err(|source| HeightfieldError::Io { path: shown.clone(), source })?;
    if let Some(problem) = crate::input::not_a_file(&meta) {
        return Err(HeightfieldError::invalid(&shown, problem));
    }
    let bytes = std::fs::read(path).map_err(|source| HeightfieldError::Io { path: shown.clone(), source })?;
    if bytes.is_empty() {
        return Err(HeightfieldError::invalid(&shown, "file is empty"));
    }
    let ext = path.extension().map(|e| e.to_string_lossy().to_lowercase()).unwrap_or_default();
    if opts.raw_size.is_some() && !matches!(ext.as_str(), "r16" | "f32") {
        // The file's own header gives its size; a size given anyway is a mistake.
        return Err(HeightfieldError::invalid(&shown, "--raw-size is only for raw .r16 and .f32 files"));
    }
    let decoded = match ext.as_str() {
        "png" | "jpg" | "jpeg" => decode_image(&shown, &bytes)?,
        "tif" | "tiff" => decode_tiff(&shown, &bytes)?,
        "r16" | "f32" => decode_raw(&shown, &bytes, &ext, opts.raw_size)?,
        "hgt" => decode_hgt(&shown, &bytes)?,
        _ => {
            return Err(HeightfieldError::invalid(
                &shown,
                format!("unknown extension '{ext}': expected .png, .jpg, .tif, .tiff, .r16, .f32 or .hgt"),
            ))
        }
    };
    if let Some(max) = opts.max_grid_side {
        let side = grid_side(decoded.width.max(decoded.height));
        if side > max {
            return Err(HeightfieldError::invalid(
                &shown,
                format!(
                    "{} x {} samples need a {side} x {side} grid, larger than the device's maxImageDimension2D ({max})",
                    decoded.width, decoded.height
                ),
            ));
        }
    }
    let (dspacing, dscale) = defaults(&shown, decoded.bits, decoded.format == HeightFormat::Float32);
    let spacing = opts.spacing.unwrap_or(dspacing);
    let height_scale = opts.height_scale.unwrap_or(dscale);
    let mut hf = Heightfield::embed(
        &shown,
        decoded.width,
        decoded.height,
        &decoded.samples,
        decoded.format,
        spacing,
        height_scale,
    )?;
    hf.void_samples = decoded.voids;
    Ok(hf)
}

struct Decoded {
    width: usize,
    height: usize,
    samples: Vec<f32>,
    format: HeightFormat,
    bits: u32,
    /// Void samples filled.
    voids: usize,
}

fn check_dims(path: &str, w: usize, h: usize) -> Result<(), HeightfieldError> {
    if w == 0 || h == 0 {
        return Err(HeightfieldError::invalid(path, format!("image is {w} x {h}: no samples")));
    }
    if w > MAX_SIDE || h > MAX_SIDE {
        return Err(HeightfieldError::invalid(
            path,
            format!("{w} x {h} is larger than the supported {MAX_SIDE} samples a side"),
        ));
    }
    Ok(())
}

fn decode_image(path: &str, bytes: &[u8]) -> Result<Decoded, HeightfieldError> {
    use image::DynamicImage as D;
    let reader = image::ImageReader::new(std::io::Cursor::new(bytes))
        .with_guessed_format()
        .map_err(|e| HeightfieldError::invalid(path, e.to_string()))?;
    let (w, h) =
        reader.into_dimensions().map_err(|e| HeightfieldError::invalid(path, format!("not a readable image: {e}")))?;
    check_dims(path, w as usize, h as usize)?;
    let img = image::ImageReader::new(std::io::Cursor::new(bytes))
        .with_guessed_format()
        .map_err(|e| HeightfieldError::invalid(path, e.to_string()))?
        .decode()
        .map_err(|e| HeightfieldError::invalid(path, format!("cannot decode image: {e}")))?;
    let (w, h) = (img.width() as usize, img.height() as usize);
    let (samples, bits): (Vec<f32>, u32) = match &img {
        D::ImageLuma8(b) => (b.as_raw().iter().map(|&v| v as f32).collect(), 8),
        D::ImageLumaA8(b) => (b.as_raw().chunks(2).map(|p| p[0] as f32).collect(), 8),
        D::ImageLuma16(b) => (b.as_raw().iter().map(|&v| v as f32).collect(), 16),
        D::ImageLumaA16(b) => (b.as_raw().chunks(2).map(|p| p[0] as f32).collect(), 16),
        D::ImageRgb8(b) => (equal_channels(path, b.as_raw(), 3, w)?, 8),
        D::ImageRgba8(b) => (equal_channels(path, b.as_raw(), 4, w)?, 8),
        D::ImageRgb16(b) => (equal_channels(path, b.as_raw(), 3, w)?, 16),
        D::ImageRgba16(b) => (equal_channels(path, b.as_raw(), 4, w)?, 16),
        _ => {
            return Err(HeightfieldError::invalid(
                path,
                format!("unsupported pixel format {:?}: expected 8- or 16-bit grayscale", img.color()),
            ))
        }
    };
    Ok(Decoded { width: w, height: h, samples, format: HeightFormat::Unorm16, bits, voids: 0 })
}

/// Published height maps are sometimes saved as RGB with R = G = B; anything else is a
/// colour picture, not heights.
fn equal_channels<T: Copy + Into<f32> + PartialEq>(
    path: &str,
    data: &[T],
    channels: usize,
    width: usize,
) -> Result<Vec<f32>, HeightfieldError> {
    let mut out = Vec::with_capacity(data.len() / channels);
    for (i, p) in data.chunks(channels).enumerate() {
        if p[0] != p[1] || p[1] != p[2] {
            return Err(HeightfieldError::invalid(
                path,
                format!(
                    "colour image (channels differ at column {}, row {}): a height map must be grayscale or have equal R, G, B",
                    i % width,
                    i / width
                ),
            ));
        }
        out.push(p[0].into());
    }
    Ok(out)
}

fn decode_tiff(path: &str, bytes: &[u8]) -> Result<Decoded, HeightfieldError> {
    use tiff::decoder::{Decoder, DecodingResult as R};
    use tiff::tags::Tag;
    let terr = |e: tiff::TiffError| HeightfieldError::invalid(path, format!("cannot decode TIFF: {e}"));
    let mut dec = Decoder::new(std::io::Cursor::new(bytes)).map_err(terr)?;
    let (w, h) = dec.dimensions().map_err(terr)?;
    let (w, h) = (w as usize, h as usize);
    check_dims(path, w, h)?;
    match dec.colortype().map_err(terr)? {
        tiff::ColorType::Gray(_) => {}
        other => {
            return Err(HeightfieldError::invalid(
                path,
                format!("unsupported TIFF colour type {other:?}: expected one grayscale band"),
            ))
        }
    }
    // GDAL_NODATA (tag 42113) is an ASCII number.
    let nodata: Option<f64> = dec
        .find_tag(Tag::Unknown(42113))
        .ok()
        .flatten()
        .and_then(|v| v.into_string().ok())
        .and_then(|s| s.trim().trim_end_matches('\0').parse::<f64>().ok());
    let image = dec.read_image().map_err(terr)?;
    let (mut samples, format, bits, void_default): (Vec<f32>, HeightFormat, u32, Option<f64>) = match image {
        R::U8(v) => (v.into_iter().map(|x| x as f32).collect(), HeightFormat::Unorm16, 8, None),
        R::U16(v) => (v.into_iter().map(|x| x as f32).collect(), HeightFormat::Unorm16, 16, None),
        R::I16(v) => (v.into_iter().map(|x| x as f32).collect(), HeightFormat::Float32, 16, Some(-32768.0)),
        R::I32(v) => (v.into_iter().map(|x| x as f32).collect(), HeightFormat::Float32, 32, None),
        R::F32(v) => (v, HeightFormat::Float32, 32, None),
        R::F64(v) => (v.into_iter().map(|x| x as f32).collect(), HeightFormat::Float32, 64, None),
        _ => {
            return Err(HeightfieldError::invalid(
                path,
                "unsupported TIFF sample type: expected 8/16-bit unsigned, 16/32-bit signed or 32/64-bit float",
            ))
        }
    };
    if samples.len() != w * h {
        return Err(HeightfieldError::invalid(
            path,
            format!("TIFF holds {} samples, expected {w} x {h}", samples.len()),
        ));
    }
    let nodata = nodata.or(void_default);
    let nan_is_void = nodata.is_some_and(|v| v.is_nan());
    if !nan_is_void {
        if let Some(i) = samples.iter().position(|v| !v.is_finite()) {
            return Err(HeightfieldError::invalid(
                path,
                format!(
                    "sample at column {}, row {} is {} (not a height, and the file declares no NaN nodata)",
                    i % w,
                    i / w,
                    samples[i]
                ),
            ));
        }
    }
    let voids = match nodata {
        Some(nd) => {
            let nd = nd as f32;
            fill_voids(path, &mut samples, w, h, |v| v == nd || (v.is_nan() && nan_is_void))?
        }
        None => 0,
    };
    Ok(Decoded { width: w, height: h, samples, format, bits, voids })
}

fn decode_raw(path: &str, bytes: &[u8], ext: &str, size: Option<(usize, usize)>) -> Result<Decoded, HeightfieldError> {
    let Some((w, h)) = size else {
        return Err(HeightfieldError::invalid(path, "raw heightfields need --raw-size WxH"));
    };
    check_dims(path, w, h)?;
    let bpp = if ext == "r16" { 2 } else { 4 };
    let expected = w * h * bpp;
    if bytes.len() != expected {
        return Err(HeightfieldError::invalid(
            path,
            format!("--raw-size {w}x{h} needs {expected} bytes of .{ext} data, the file has {}", bytes.len()),
        ));
    }
    let (samples, format, bits) = if bpp == 2 {
        (bytes.chunks_exact(2).map(|c| u16::from_le_bytes([c[0], c[1]]) as f32).collect(), HeightFormat::Unorm16, 16)
    } else {
        (
            bytes.chunks_exact(4).map(|c| f32::from_le_bytes([c[0], c[1], c[2], c[3]])).collect(),
            HeightFormat::Float32,
            32,
        )
    };
    Ok(Decoded { width: w, height: h, samples, format, bits, voids: 0 })
}

fn decode_hgt(path: &str, bytes: &[u8]) -> Result<Decoded, HeightfieldError> {
    let side = match bytes.len() {
        n if n == 1201 * 1201 * 2 => 1201,
        n if n == 3601 * 3601 * 2 => 3601,
        n => {
            return Err(HeightfieldError::invalid(
                path,
                format!(
                    "SRTM .hgt files are 1201 x 1201 ({} bytes) or 3601 x 3601 ({} bytes); this one has {n} bytes",
                    1201 * 1201 * 2,
                    3601 * 3601 * 2
                ),
            ))
        }
    };
    let mut samples: Vec<f32> = bytes.chunks_exact(2).map(|c| i16::from_be_bytes([c[0], c[1]]) as f32).collect();
    let voids = fill_voids(path, &mut samples, side, side, |v| v == -32768.0)?;
    Ok(Decoded { width: side, height: side, samples, format: HeightFormat::Float32, bits: 16, voids })
}

/// Fills the voids (nodata samples) smoothly and returns how many there were: each void
/// gets the solution of Laplace's equation with the valid samples around it as boundary
/// values (a membrane stretched over the hole, as GDAL's fill-nodata smooths its
/// inverse-distance guess), so a filled region has no step the data around it does not
/// have: a harmonic fill takes its extremes on its boundary. Samples on the grid's edge
/// use the neighbours they have. Solved by over-relaxed Gauss-Seidel from a first guess
/// made in waves (each void that touches filled samples gets their mean).
pub fn fill_voids(
    path: &str,
    samples: &mut [f32],
    w: usize,
    h: usize,
    is_void: impl Fn(f32) -> bool,
) -> Result<usize, HeightfieldError> {
    let void: Vec<bool> = samples.iter().map(|&v| is_void(v)).collect();
    let voids: Vec<usize> = (0..samples.len()).filter(|&i| void[i]).collect();
    if voids.is_empty() {
        return Ok(0);
    }
    if voids.len() == samples.len() {
        return Err(HeightfieldError::invalid(path, "every sample is a void (nodata)"));
    }
    let neighbours = |i: usize| {
        let (x, z) = (i % w, i / w);
        [(x > 0).then(|| i - 1), (x + 1 < w).then(|| i + 1), (z > 0).then(|| i - w), (z + 1 < h).then(|| i + w)]
    };
    wave_fill(samples, &void, &voids, neighbours);
    // Over-relaxation (omega near 2 for wide holes); stops when no sample moves by more
    // than a millionth of the data's range, or after a bounded number of sweeps.
    let (lo, hi) = samples.iter().fold((f32::INFINITY, f32::NEG_INFINITY), |(a, b), &v| (a.min(v), b.max(v)));
    let tolerance = ((hi - lo) as f64 * 1e-6).max(1e-6);
    let mut values: Vec<f64> = samples.iter().map(|&v| v as f64).collect();
    let around: Vec<[Option<usize>; 4]> = voids.iter().map(|&i| neighbours(i)).collect();
    let omega = 1.9;
    for _ in 0..20_000 {
        let mut largest = 0.0f64;
        for (&i, nb) in voids.iter().zip(&around) {
            let (mut sum, mut count) = (0.0, 0.0);
            for j in nb.iter().flatten() {
                sum += values[*j];
                count += 1.0;
            }
            let step = omega * (sum / count - values[i]);
            values[i] += step;
            largest = largest.max(step.abs());
        }
        if largest < tolerance {
            break;
        }
    }
    for &i in &voids {
        samples[i] = values[i] as f32;
    }
    Ok(voids.len())
}

/// The first guess: in waves from the valid samples, each void that touches filled ones
/// takes their mean.
fn wave_fill(samples: &mut [f32], void: &[bool], voids: &[usize], neighbours: impl Fn(usize) -> [Option<usize>; 4]) {
    let mut filled: Vec<bool> = void.iter().map(|v| !v).collect();
    let mut frontier = voids.to_vec();
    while !frontier.is_empty() {
        let mut updates = Vec::new();
        let mut rest = Vec::new();
        for &i in &frontier {
            let (mut sum, mut count) = (0.0f64, 0u32);
            for j in neighbours(i).into_iter().flatten() {
                if filled[j] {
                    sum += samples[j] as f64;
                    count += 1;
                }
            }
            if count > 0 {
                updates.push((i, (sum / count as f64) as f32));
            } else {
                rest.push(i);
            }
        }
        for (i, v) in updates {
            samples[i] = v;
            filled[i] = true;
        }
        frontier = rest;
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A plane with a hole is filled with the plane (a harmonic function is its own
    /// Laplace fill), to within the solver's tolerance; the count is the hole's size.
    #[test]
    fn a_hole_in_a_plane_is_filled_with_the_plane() {
        let (w, h) = (40, 30);
        let plane = |x: usize, z: usize| 3.0 * x as f32 - 2.0 * z as f32 + 100.0;
        let mut s: Vec<f32> = (0..w * h).map(|i| plane(i % w, i / w)).collect();
        let hole = |x: usize, z: usize| (8..30).contains(&x) && (5..25).contains(&z);
        for z in 0..h {
            for x in 0..w {
                if hole(x, z) {
                    s[z * w + x] = -32768.0;
                }
            }
        }
        let n = fill_voids("t", &mut s, w, h, |v| v == -32768.0).unwrap();
        assert_eq!(n, 22 * 20);
        for z in 0..h {
            for x in 0..w {
                assert!((s[z * w + x] - plane(x, z)).abs() < 0.01, "({x}, {z}): {} for {}", s[z * w + x], plane(x, z));
            }
        }
    }

    #[test]
    fn voids_are_filled_from_neighbours() {
        let mut s = vec![1.0, -32768.0, 3.0, -32768.0, -32768.0, -32768.0, 7.0, 8.0, 9.0];
        let n = fill_voids("t", &mut s, 3, 3, |v| v == -32768.0).unwrap();
        assert_eq!(n, 4);
        assert!(s.iter().all(|v| (1.0..=9.0).contains(v)), "{s:?}");
    }

    #[test]
    fn all_void_is_an_error() {
        let mut s = vec![-32768.0; 9];
        assert!(fill_voids("t.hgt", &mut s, 3, 3, |v| v == -32768.0).is_err());
    }
}
