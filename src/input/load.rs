//! Heightfield loaders: everything GDAL reads (GeoTIFF, SRTM `.hgt`, PNG and JPEG with
//! or without world files, VRT, ...: [`georef`]), and raw `.r16` / `.f32`; voids filled.

use crate::input::georef;
use crate::lod::heightfield::{grid_side, HeightFormat, Heightfield, HeightfieldError, Spacing, MAX_SIDE};
use std::path::Path;

/// Options shared by every subcommand that loads a heightfield.
#[derive(Clone, Debug, Default)]
pub struct LoadOptions {
    /// Metres between samples (x, z); `None` takes the file's georeferencing.
    pub spacing: Option<Spacing>,
    /// World units per raw unit; `None` picks the default.
    pub height_scale: Option<f32>,
    /// Size of a raw `.r16`/`.f32` file.
    pub raw_size: Option<(usize, usize)>,
    /// The device's maxImageDimension2D, when known: checked before the grid is
    /// allocated.
    pub max_grid_side: Option<usize>,
    /// What voids (nodata) become.
    pub voids: VoidMode,
}

/// What the renderer draws where the file has no data.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, clap::ValueEnum, serde::Serialize)]
#[serde(rename_all = "lowercase")]
pub enum VoidMode {
    /// Filled smoothly (Laplace) and drawn as terrain.
    #[default]
    Fill,
    /// Filled for the LOD machinery, but cut out of the picture.
    Hole,
}

/// Loads a heightfield file; every error names the file and the problem. What the file
/// says about itself (georeferencing, units, nodata) is read first ([`georef`]) and
/// recorded in the heightfield's `georef.notes`, which the front-ends print.
pub fn load(path: &Path, opts: &LoadOptions) -> Result<Heightfield, HeightfieldError> {
    let shown = path.display().to_string();
    let meta = std::fs::metadata(path).map_err(|source| HeightfieldError::Io { path: shown.clone(), source })?;
    if let Some(problem) = crate::input::not_a_file(&meta) {
        return Err(HeightfieldError::invalid(&shown, problem));
    }
    if meta.len() == 0 {
        return Err(HeightfieldError::invalid(&shown, "file is empty"));
    }
    let ext = path.extension().map(|e| e.to_string_lossy().to_lowercase()).unwrap_or_default();
    if opts.raw_size.is_some() && !matches!(ext.as_str(), "r16" | "f32") {
        // The file's own header gives its size; a size given anyway is a mistake.
        return Err(HeightfieldError::invalid(&shown, "--raw-size is only for raw .r16 and .f32 files"));
    }
    let mut raster = match ext.as_str() {
        "r16" | "f32" => {
            let bytes = std::fs::read(path).map_err(|source| HeightfieldError::Io { path: shown.clone(), source })?;
            decode_raw(&shown, &bytes, &ext, opts.raw_size)?
        }
        _ => {
            if ext == "hgt" {
                check_hgt(&shown, path, meta.len())?;
            }
            georef::read(path)?
        }
    };
    check_dims(&shown, raster.width, raster.height)?;
    if let Some(max) = opts.max_grid_side {
        let side = grid_side(raster.width.max(raster.height));
        if side > max {
            return Err(HeightfieldError::invalid(
                &shown,
                format!(
                    "{} x {} samples need a {side} x {side} grid, larger than the device's maxImageDimension2D ({max})",
                    raster.width, raster.height
                ),
            ));
        }
    }
    // Only files without georeferencing are looked up among the known data sets (their
    // scale is documented beside them, not in them).
    let known = if raster.transform.is_none() && raster.crs_wkt.is_none() {
        let bytes = std::fs::read(path).map_err(|source| HeightfieldError::Io { path: shown.clone(), source })?;
        georef::known_dataset(&bytes)
    } else {
        None
    };
    let scale = georef::decide(&shown, &raster, opts.spacing, opts.height_scale, known)?;
    let (voids, mask) = fill_file_voids(&shown, &mut raster, opts.voids)?;
    let mut hf = Heightfield::embed(
        &shown,
        raster.width,
        raster.height,
        &raster.samples,
        raster.format,
        scale.spacing,
        scale.height_scale,
    )?;
    hf.void_samples = voids;
    hf.void_mask = mask;
    hf.georef = scale.georef;
    Ok(hf)
}

/// SRTM tiles are 1201 or 3601 samples a side and placed by their name.
fn check_hgt(shown: &str, path: &Path, len: u64) -> Result<(), HeightfieldError> {
    if len != 1201 * 1201 * 2 && len != 3601 * 3601 * 2 {
        return Err(HeightfieldError::invalid(
            shown,
            format!(
                "SRTM .hgt files are 1201 x 1201 ({} bytes) or 3601 x 3601 ({} bytes); this one has {len} bytes",
                1201 * 1201 * 2,
                3601 * 3601 * 2
            ),
        ));
    }
    let name = path.file_stem().map(|s| s.to_string_lossy().to_uppercase()).unwrap_or_default();
    let b = name.as_bytes();
    let placed = b.len() >= 7
        && matches!(b[0], b'N' | b'S')
        && b[1..3].iter().all(u8::is_ascii_digit)
        && matches!(b[3], b'E' | b'W')
        && b[4..7].iter().all(u8::is_ascii_digit);
    if !placed {
        return Err(HeightfieldError::invalid(
            shown,
            "an SRTM .hgt tile is placed by its name (its south-west corner, like N46W122.hgt), and this name places it nowhere: rename it",
        ));
    }
    Ok(())
}

/// Applies the band's offset (in raw units, so that `raw * height_scale` stays the
/// height), rejects non-finite samples the file does not call nodata, and fills the
/// voids; returns how many there were, and with [`VoidMode::Hole`] which they were.
fn fill_file_voids(
    shown: &str,
    r: &mut georef::Raster,
    mode: VoidMode,
) -> Result<(usize, Option<Vec<bool>>), HeightfieldError> {
    // Signed 16-bit rasters without a declared nodata: SRTM's void value.
    let nodata = r.nodata.or((r.format == HeightFormat::Float32 && r.bits == 16).then_some(-32768.0));
    let nan_is_void = nodata.is_some_and(|v| v.is_nan());
    if !nan_is_void {
        if let Some(i) = r.samples.iter().position(|v| !v.is_finite()) {
            return Err(HeightfieldError::invalid(
                shown,
                format!(
                    "sample at column {}, row {} is {} (not a height, and the file declares no NaN nodata)",
                    i % r.width,
                    i / r.width,
                    r.samples[i]
                ),
            ));
        }
    }
    let is_void = |v: f32| match nodata {
        Some(nd) if nd.is_nan() => v.is_nan(),
        Some(nd) => v == nd as f32,
        None => false,
    };
    if let Some(offset) = r.offset {
        let raw_offset = (offset / r.scale.unwrap_or(1.0)) as f32;
        for v in r.samples.iter_mut().filter(|v| !is_void(**v)) {
            *v += raw_offset;
        }
        r.format = HeightFormat::Float32;
    }
    let mask = (mode == VoidMode::Hole).then(|| r.samples.iter().map(|&v| is_void(v)).collect::<Vec<bool>>());
    let n = fill_voids(shown, &mut r.samples, r.width, r.height, is_void)?;
    Ok((n, mask.filter(|_| n > 0)))
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

fn decode_raw(
    path: &str,
    bytes: &[u8],
    ext: &str,
    size: Option<(usize, usize)>,
) -> Result<georef::Raster, HeightfieldError> {
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
    Ok(georef::Raster {
        width: w,
        height: h,
        samples,
        format,
        bits,
        nodata: None,
        scale: None,
        offset: None,
        vertical_unit: None,
        driver: "raw".into(),
        transform: None,
        crs_wkt: None,
        outside: 0,
    })
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
