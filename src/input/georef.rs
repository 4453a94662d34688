//! What a file says about where it is and what its numbers mean (SPEC section 9), read
//! through GDAL: the reader QGIS and most GIS tools use, so that whatever opens there
//! (GeoTIFF and BigTIFF with their GeoKeys, SRTM `.hgt` placed by its name, PNG or JPEG
//! with a world file and `.prj`, VRT mosaics, cloud-optimised GeoTIFF, some 200 formats)
//! opens here with the same georeferencing, nodata, scale and offset.
//!
//! Then the world frame: a projected CRS gives metres per sample directly (feet and other
//! units converted); a geographic one gives degrees, which become metres per axis at the
//! extent's centre latitude on the CRS's own ellipsoid, or, when one spacing per axis is off
//! by more than [`MAX_STRETCH`] somewhere, the raster is warped to a local transverse
//! Mercator projection first.

use crate::lod::heightfield::{Georef, HeightFormat, HeightfieldError, Spacing, MAX_SIDE};
use gdal::raster::GdalDataType;
use gdal::spatial_ref::SpatialRef;
use gdal::Dataset;
use std::path::Path;
use std::sync::Once;

/// The largest relative error of one spacing per axis, anywhere in the extent, before a
/// geographic raster is reprojected instead.
pub const MAX_STRETCH: f64 = 0.01;

/// A raster band of heights as GDAL read it, with what the file says about it.
pub struct Raster {
    pub width: usize,
    pub height: usize,
    /// Row-major, `width * height`, the file's own numbers (no scale or offset applied).
    pub samples: Vec<f32>,
    pub format: HeightFormat,
    /// Bits per sample in the file.
    pub bits: u32,
    /// The band's nodata value, if it declares one (NaN included).
    pub nodata: Option<f64>,
    /// Band scale and offset (height = value * scale + offset, in `unit`).
    pub scale: Option<f64>,
    pub offset: Option<f64>,
    /// Metres per height unit, from the band's unit type or the vertical CRS, with the
    /// unit's name.
    pub vertical_unit: Option<(f64, String)>,
    /// GDAL's driver, for messages ("GTiff", "SRTMHGT", "PNG").
    pub driver: String,
    /// The geotransform, when the file has one.
    pub transform: Option<[f64; 6]>,
    /// Where the geotransform came from, for messages ("the GeoTIFF tags", "the world
    /// file x.pgw", "the file's header").
    pub transform_from: String,
    /// The CRS, when the file has one (WKT), and its name when it has no code (the local
    /// projection of a reprojected raster, as its PROJ string).
    pub crs_wkt: Option<String>,
    pub crs_name: Option<String>,
    /// Samples that lie outside the source raster after a reprojection: how many, and
    /// which (drawn as holes whatever `--voids` says: nothing outside the data is drawn).
    pub outside: usize,
    pub outside_mask: Option<Vec<bool>>,
    /// The file's nodata when the raster was reprojected (its `nodata` is then NaN).
    pub reprojected_nodata: Option<f64>,
    /// What reading did to the samples, for the load message.
    pub notes: Vec<String>,
}

/// GDAL reports problems both as return values (which become our messages) and through
/// its error handler, which by default prints them; route the printed copies to
/// `tracing` so that a bad file produces one message, ours. Also ask the GeoTIFF driver
/// for the vertical part of a compound CRS (the vertical units).
fn init_gdal() {
    static INIT: Once = Once::new();
    INIT.call_once(|| {
        gdal::config::set_error_handler(|class, code, msg| {
            tracing::debug!("GDAL {class:?} {code}: {msg}");
        });
        // A failure here only loses the vertical units of compound CRSs.
        let _ = gdal::config::set_config_option("GTIFF_REPORT_COMPD_CS", "YES");
    });
}

/// GDAL's own words for a failure, without the file name it repeats.
fn gdal_message(shown: &str, e: gdal::errors::GdalError) -> String {
    use gdal::errors::GdalError as E;
    let msg = match e {
        E::CplError { msg, .. } => msg,
        E::NullPointer { msg, .. } => msg,
        other => other.to_string(),
    };
    let msg = msg.trim();
    let msg = msg.strip_prefix(shown).map(|m| m.trim_start_matches([':', ',', ' '])).unwrap_or(msg);
    if msg.is_empty() {
        "no GDAL driver recognises it".into()
    } else {
        msg.to_string()
    }
}

/// Metres per unit of a vertical unit's name, for the names GDAL and PROJ use.
pub fn metres_per_unit(name: &str) -> Option<f64> {
    let n = name.trim().to_lowercase();
    match n.as_str() {
        "m" | "metre" | "metres" | "meter" | "meters" => Some(1.0),
        "ft" | "foot" | "feet" | "international foot" | "foot (international)" => Some(0.3048),
        "us-ft" | "ftus" | "us survey foot" | "us_survey_foot" | "foot_us" | "foot (us survey)" => {
            Some(1200.0 / 3937.0)
        }
        "cm" | "centimetre" | "centimeter" => Some(0.01),
        "dm" | "decimetre" | "decimeter" => Some(0.1),
        "mm" | "millimetre" | "millimeter" => Some(0.001),
        "km" | "kilometre" | "kilometer" => Some(1000.0),
        _ => None,
    }
}

/// The vertical CRS's unit in a compound CRS, from its PROJJSON.
fn vertical_crs_unit(srs: &SpatialRef) -> Option<(f64, String)> {
    let json: serde_json::Value = serde_json::from_str(&srs.to_projjson().ok()?).ok()?;
    let vertical = json["components"].as_array()?.iter().find(|c| c["type"] == "VerticalCRS")?;
    let unit = &vertical["coordinate_system"]["axis"][0]["unit"];
    match unit {
        serde_json::Value::String(name) => metres_per_unit(name).map(|m| (m, name.clone())),
        serde_json::Value::Object(o) => {
            let name = o.get("name")?.as_str()?.to_string();
            Some((o.get("conversion_factor")?.as_f64()?, name))
        }
        _ => None,
    }
}

/// "EPSG:32610"; a compound CRS without a code of its own as its parts' codes joined by
/// "+" ("EPSG:2227+8228", as PROJ writes them); else the CRS's name.
fn crs_label(srs: &SpatialRef) -> String {
    if let (Some(a), Ok(c)) = (srs.auth_name(), srs.auth_code()) {
        return format!("{a}:{c}");
    }
    let parts: Option<Vec<String>> = (|| {
        let json: serde_json::Value = serde_json::from_str(&srs.to_projjson().ok()?).ok()?;
        json["components"]
            .as_array()?
            .iter()
            .map(|c| Some(format!("{}:{}", c["id"]["authority"].as_str()?, c["id"]["code"])))
            .collect()
    })();
    match parts {
        Some(p) if !p.is_empty() => {
            let (first, rest) = p.split_first().expect("not empty");
            let authority = first.split(':').next().unwrap_or_default().to_string();
            let codes: Vec<String> =
                rest.iter().map(|r| r.trim_start_matches(&format!("{authority}:")).to_string()).collect();
            std::iter::once(first.clone()).chain(codes).collect::<Vec<_>>().join("+")
        }
        _ => srs.name().unwrap_or_else(|| "unnamed CRS".into()),
    }
}

/// Opens `path` with GDAL and reads its height band and what it says about itself.
pub fn read(path: &Path) -> Result<Raster, HeightfieldError> {
    let shown = path.display().to_string();
    let bad = |m: String| HeightfieldError::invalid(&shown, m);
    let why = |e: gdal::errors::GdalError| gdal_message(&shown, e);
    let ds = open(path)?;
    let (w, h) = ds.raster_size();
    if w > MAX_SIDE || h > MAX_SIDE {
        return Err(bad(format!(
            "{w} x {h} is larger than the supported {MAX_SIDE} samples a side (`vkterrain prepare` makes an archive of it)"
        )));
    }
    let bands = ds.raster_count();
    let read_band = |i: usize| -> Result<Vec<f32>, HeightfieldError> {
        let b = ds.rasterband(i).map_err(|e| bad(format!("cannot decode band {i}: {}", why(e))))?;
        let buf = b
            .read_as::<f32>((0, 0), (w, h), (w, h), None)
            .map_err(|e| bad(format!("cannot decode band {i}: {}", why(e))))?;
        Ok(buf.into_shape_and_vec().1)
    };
    let samples = match bands {
        1 | 2 => read_band(1)?, // gray, or gray and alpha
        3 | 4 => {
            // Published height maps are sometimes saved as RGB with R = G = B; anything
            // else is a colour picture, not heights.
            let r = read_band(1)?;
            for c in 2..=3 {
                let other = read_band(c)?;
                if let Some(i) = (0..r.len()).find(|&i| r[i] != other[i]) {
                    return Err(bad(format!(
                        "colour image (channels differ at column {}, row {}): a height map must be grayscale or have equal R, G, B",
                        i % w,
                        i / w
                    )));
                }
            }
            r
        }
        n => return Err(bad(format!("{n} bands: expected one band of heights (or equal R, G, B)"))),
    };
    let (mut raster, srs) = header(path, &ds)?;
    raster.samples = samples;
    if let (Some(t), Some(s)) = (&raster.transform, &srs) {
        if s.is_geographic() && t[2] == 0.0 && t[4] == 0.0 {
            let frame = geographic_frame(t, w, h, s);
            if frame.worst_stretch > MAX_STRETCH {
                return reproject(&shown, &ds, raster, s, &frame);
            }
        }
    }
    orient_east_and_south(&mut raster);
    Ok(raster)
}

fn open(path: &Path) -> Result<Dataset, HeightfieldError> {
    init_gdal();
    let shown = path.display().to_string();
    // GDAL reports an unreadable file as one no driver recognises: say what the OS says.
    if let Err(source) = std::fs::File::open(path) {
        return Err(HeightfieldError::Io { path: shown, source });
    }
    let ds = Dataset::open(path).map_err(|e| {
        HeightfieldError::invalid(
            &shown,
            format!(
                "not a raster I can read: {} (GeoTIFF, SRTM .hgt, PNG, JPEG and the other GDAL rasters are; raw .r16/.f32 need --raw-size)",
                gdal_message(&shown, e)
            ),
        )
    })?;
    let (w, h) = ds.raster_size();
    if w == 0 || h == 0 {
        return Err(HeightfieldError::invalid(&shown, format!("image is {w} x {h}: no samples")));
    }
    // GDAL's JPEG driver decodes a cut-off file with a warning and grey rows after the
    // cut; a complete JPEG ends with the end-of-image marker.
    if ds.driver().short_name() == "JPEG" && !jpeg_complete(path) {
        return Err(HeightfieldError::invalid(
            &shown,
            "the JPEG is truncated (it does not end with the end-of-image marker FF D9)",
        ));
    }
    Ok(ds)
}

/// The world file beside `path` (as GDAL looks for one), if there is one.
fn world_file(path: &Path) -> Option<std::path::PathBuf> {
    let stem = path.with_extension("");
    ["wld", "pgw", "pngw", "jgw", "jpgw", "tfw", "tifw"]
        .into_iter()
        .map(|ext| stem.with_extension(ext))
        .find(|wf| wf.is_file())
}

/// Does the file end with a JPEG end-of-image marker (trailing padding allowed)?
fn jpeg_complete(path: &Path) -> bool {
    use std::io::{Read, Seek, SeekFrom};
    let Ok(mut f) = std::fs::File::open(path) else { return false };
    let Ok(len) = f.seek(SeekFrom::End(0)) else { return false };
    let tail_len = len.min(4096);
    let mut tail = vec![0u8; tail_len as usize];
    if f.seek(SeekFrom::Start(len - tail_len)).is_err() || f.read_exact(&mut tail).is_err() {
        return false;
    }
    tail.windows(2).any(|w| w == [0xFF, 0xD9])
}

/// Everything the file says about its samples but the samples (left empty): type,
/// nodata, scale and offset, units, transform, CRS; the georeferencing checked.
fn header(path: &Path, ds: &Dataset) -> Result<(Raster, Option<SpatialRef>), HeightfieldError> {
    let shown = path.display().to_string();
    let bad = |m: String| HeightfieldError::invalid(&shown, m);
    let why = |e: gdal::errors::GdalError| gdal_message(&shown, e);
    let (w, h) = ds.raster_size();
    let band = ds.rasterband(1).map_err(|e| bad(format!("cannot decode band 1: {}", why(e))))?;
    let (format, bits) = match band.band_type() {
        GdalDataType::UInt8 => (HeightFormat::Unorm16, 8),
        GdalDataType::UInt16 => (HeightFormat::Unorm16, 16),
        GdalDataType::Int16 => (HeightFormat::Float32, 16),
        GdalDataType::UInt32 | GdalDataType::Int32 | GdalDataType::Float32 => (HeightFormat::Float32, 32),
        GdalDataType::UInt64 | GdalDataType::Int64 | GdalDataType::Float64 => (HeightFormat::Float32, 64),
        other => return Err(bad(format!("unsupported sample type {other:?}: expected integers or floats"))),
    };
    let mut notes = Vec::new();
    // A .prj beside the file (as QGIS reads it) when the file itself names no CRS.
    let srs = ds.spatial_ref().ok().or_else(|| {
        let prj = path.with_extension("prj");
        let text = std::fs::read_to_string(&prj).ok()?;
        let s = SpatialRef::from_esri(&text).or_else(|_| SpatialRef::from_definition(text.trim())).ok()?;
        notes.push(format!("CRS from {}", prj.display()));
        Some(s)
    });
    // GDAL answers a default transform with an error when the file has none.
    let transform = ds.geo_transform().ok();
    if transform.is_none() {
        if !ds.gcps().is_empty() {
            return Err(bad(format!(
                "no usable geotransform: georeferenced by {} ground control point(s) only, or a zero pixel size: warp it to a grid first (gdalwarp)",
                ds.gcps().len()
            )));
        }
        if srs.is_some() {
            return Err(bad(
                "it names a CRS but has no usable geotransform (a zero pixel size?): its georeferencing is broken"
                    .into(),
            ));
        }
        if let Some(wf) = world_file(path) {
            return Err(bad(format!("its world file {} could not be used (a zero pixel size?)", wf.display())));
        }
    }
    let transform_from = match (world_file(path), ds.driver().short_name().as_str()) {
        (Some(wf), _) => format!("the world file {}", wf.display()),
        (None, "GTiff" | "COG") => "the GeoTIFF tags".to_string(),
        (None, _) => "the file's header".to_string(),
    };
    let unit_name = band.unit();
    let vertical_unit = match metres_per_unit(&unit_name) {
        Some(m) => Some((m, unit_name)),
        None if !unit_name.trim().is_empty() => {
            return Err(bad(format!("height unit '{unit_name}' is not one I know (metres, feet, ...)")))
        }
        None => srs.as_ref().and_then(vertical_crs_unit),
    };
    if band.scale() == Some(0.0) {
        return Err(bad("its band scale is 0: every height would be 0".into()));
    }
    let raster = Raster {
        width: w,
        height: h,
        samples: Vec::new(),
        format,
        bits,
        nodata: band.no_data_value(),
        scale: band.scale().filter(|s| *s != 1.0),
        offset: band.offset().filter(|o| *o != 0.0),
        vertical_unit,
        driver: ds.driver().short_name(),
        transform,
        transform_from,
        crs_wkt: srs.as_ref().and_then(|s| s.to_wkt().ok()),
        crs_name: None,
        outside: 0,
        outside_mask: None,
        reprojected_nodata: None,
        notes,
    };
    if let (Some(t), Some(s)) = (&raster.transform, &srs) {
        if s.is_geographic() {
            // Sample centres' latitudes: beyond a pole the georeferencing is wrong.
            let unit = if s.angular_units() > 0.0 { s.angular_units().to_degrees() } else { 1.0 };
            let lats = [t[3] + 0.5 * t[5], t[3] + (h as f64 - 0.5) * t[5]].map(|v| v * unit);
            if lats.iter().any(|l| !(-90.0..=90.0).contains(l)) {
                return Err(bad(format!(
                    "its georeferencing puts samples at latitude {:.4} to {:.4}: beyond a pole",
                    lats[0].min(lats[1]),
                    lats[0].max(lats[1])
                )));
            }
        }
    }
    Ok((raster, srs))
}

/// A raster read window by window (`vkterrain prepare` on inputs of any size): the
/// file's header as [`read`] takes it, samples on demand, mirrored east and south like
/// [`orient_east_and_south`], the band offset applied. Voids are refused where found
/// (filling them needs their surroundings: inputs that fit in memory are filled).
pub struct WindowReader {
    path: std::path::PathBuf,
    /// Open datasets, one per thread reading at a time (a GDAL dataset is not `Sync`).
    pool: std::sync::Mutex<Vec<Dataset>>,
    /// The header; `samples` stays empty.
    pub raster: Raster,
    flip: [bool; 2],
    raw_offset: f32,
    nodata: Option<f64>,
    /// RGB(A): heights only where R = G = B, checked in every window.
    colour_bands: bool,
}

/// Extensions a directory given to `prepare` is searched for (elevation tiles GDAL reads).
pub const TILE_EXTENSIONS: &[&str] = &["hgt", "tif", "tiff", "dem", "img", "bil", "asc", "vrt"];

/// Many rasters as one, mosaicked by their georeferencing: a GDAL VRT written to `vrt`
/// (as `gdalbuildvrt` would). Every input must open, carry georeferencing and share the
/// first one's CRS, band count and resolution (GDAL would skip such a file with a
/// warning, or resample every tile: here it is an error naming it, never a silent hole
/// or a changed sample).
pub fn mosaic(inputs: &[std::path::PathBuf], vrt: &Path) -> Result<(), HeightfieldError> {
    init_gdal();
    let mut datasets = Vec::with_capacity(inputs.len());
    // The first tile's name, CRS, band count, sample step and origin.
    type First = (String, SpatialRef, usize, [f64; 2], [f64; 2]);
    let mut first: Option<First> = None;
    let mut absolute = Vec::with_capacity(inputs.len());
    for path in inputs {
        let shown = path.display().to_string();
        let bad = |m: String| HeightfieldError::invalid(&shown, m);
        // Absolute, so that the VRT names it as given and can be checked below.
        let path =
            &std::fs::canonicalize(path).map_err(|source| HeightfieldError::Io { path: shown.clone(), source })?;
        absolute.push((shown.clone(), path.clone()));
        let ds = open(path)?;
        let Ok(t) = ds.geo_transform() else {
            return Err(bad("has no georeferencing: a mosaic places its tiles by it".into()));
        };
        let srs = ds.spatial_ref().map_err(|_| bad("has no CRS: a mosaic places its tiles by it".into()))?;
        let bands = ds.raster_count();
        match &first {
            None => first = Some((shown.clone(), srs, bands, [t[1], t[5]], [t[0], t[3]])),
            Some((name, crs, n, step, origin)) => {
                if !srs_same(crs, &srs) {
                    return Err(bad(format!(
                        "its CRS ({}) differs from {name}'s ({}): reproject the tiles to one CRS first",
                        crs_label(&srs),
                        crs_label(crs)
                    )));
                }
                if bands != *n {
                    return Err(bad(format!("{bands} bands, {name} has {n}")));
                }
                // GDAL would resample every tile to an average resolution.
                let same = |a: f64, b: f64| (a - b).abs() <= 1e-9 * a.abs().max(b.abs());
                if !(same(t[1], step[0]) && same(t[5], step[1])) {
                    return Err(bad(format!(
                        "its samples are {} x {} apart, {name}'s {} x {}: a mosaic needs one resolution (resample the tiles first)",
                        t[1], t[5], step[0], step[1]
                    )));
                }
                // On the first tile's grid: else GDAL shifts it by a fraction of a sample.
                let offset = [(t[0] - origin[0]) / step[0], (t[3] - origin[1]) / step[1]];
                if offset.iter().any(|o| (o - o.round()).abs() > 1e-6) {
                    return Err(bad(format!(
                        "its samples lie {:.4} x {:.4} samples off {name}'s grid: a mosaic needs one grid (resample the tiles first)",
                        offset[0] - offset[0].round(),
                        offset[1] - offset[1].round()
                    )));
                }
            }
        }
        datasets.push(ds);
    }
    let shown = vrt.display().to_string();
    let built = gdal::programs::raster::build_vrt(Some(vrt), &datasets, None)
        .map_err(|e| HeightfieldError::invalid(&shown, format!("building the mosaic: {}", gdal_message(&shown, e))))?;
    drop(built); // writes the VRT
                 // GDAL leaves out, with only a warning, a tile it finds unlike the first (data type,
                 // nodata, colour interpretation): every tile must be among the VRT's sources.
    let text = std::fs::read_to_string(vrt).map_err(|source| HeightfieldError::Io { path: shown.clone(), source })?;
    let first_name = absolute.first().map(|a| a.0.clone()).unwrap_or_default();
    for (name, path) in &absolute {
        if !text.contains(&format!(">{}<", path.display())) {
            return Err(HeightfieldError::invalid(
                name,
                format!(
                    "GDAL left it out of the mosaic: unlike {first_name} in data type, nodata or colour interpretation (convert the tiles to one format first)"
                ),
            ));
        }
    }
    Ok(())
}

fn srs_same(a: &SpatialRef, b: &SpatialRef) -> bool {
    match (a.to_wkt(), b.to_wkt()) {
        (Ok(x), Ok(y)) => x == y,
        _ => false,
    }
}

impl WindowReader {
    pub fn open(path: &Path) -> Result<WindowReader, HeightfieldError> {
        let shown = path.display().to_string();
        let bad = |m: String| HeightfieldError::invalid(&shown, m);
        let ds = open(path)?;
        let bands = ds.raster_count();
        if bands > 4 {
            return Err(bad(format!("{bands} bands: expected one band of heights (or equal R, G, B)")));
        }
        let (mut raster, srs) = header(path, &ds)?;
        if let (Some(t), Some(s)) = (&raster.transform, &srs) {
            if s.is_geographic() && t[2] == 0.0 && t[4] == 0.0 {
                let frame = geographic_frame(t, raster.width, raster.height, s);
                if frame.worst_stretch > MAX_STRETCH {
                    return Err(bad(format!(
                        "one spacing per axis is off by {:.1} % over this geographic extent: it needs reprojecting, \
                         which window-by-window reading does not do (gdalwarp -t_srs to a metric projection first)",
                        100.0 * frame.worst_stretch
                    )));
                }
            }
        }
        let t = raster.transform.unwrap_or([0.0, 1.0, 0.0, 0.0, 0.0, -1.0]);
        let flip = [t[1] < 0.0, t[5] > 0.0];
        orient_east_and_south(&mut raster);
        let nodata =
            raster.nodata.or((raster.format == HeightFormat::Float32 && raster.bits == 16).then_some(-32768.0));
        let raw_offset = raster.offset.map_or(0.0, |o| (o / raster.scale.unwrap_or(1.0)) as f32);
        if raster.offset.is_some() {
            raster.format = HeightFormat::Float32;
        }
        // GDAL's block cache is the only memory here that grows with the file.
        let _ = gdal::config::set_config_option("GDAL_CACHEMAX", "256");
        Ok(WindowReader {
            path: path.to_path_buf(),
            pool: std::sync::Mutex::new(vec![ds]),
            raster,
            flip,
            raw_offset,
            nodata,
            colour_bands: bands >= 3,
        })
    }

    pub fn path(&self) -> &Path {
        &self.path
    }

    /// Samples `x0..=x1`, `z0..=z1` (inside the extent, east and south oriented),
    /// row-major.
    pub fn read(&self, x0: usize, z0: usize, x1: usize, z1: usize) -> Result<Vec<f32>, String> {
        let shown = self.path.display().to_string();
        let (w, h) = (self.raster.width, self.raster.height);
        let (nx, nz) = (x1 - x0 + 1, z1 - z0 + 1);
        // The same box in the file's own orientation.
        let fx = if self.flip[0] { w - 1 - x1 } else { x0 };
        let fz = if self.flip[1] { h - 1 - z1 } else { z0 };
        let ds = match self.pool.lock().expect("dataset pool").pop() {
            Some(ds) => ds,
            None => open(&self.path).map_err(|e| e.to_string())?,
        };
        let band = |i: usize| {
            ds.rasterband(i)
                .and_then(|b| b.read_as::<f32>((fx as isize, fz as isize), (nx, nz), (nx, nz), None))
                .map(|b| b.into_shape_and_vec().1)
        };
        let read = band(1).and_then(|v| {
            let others = if self.colour_bands { vec![band(2)?, band(3)?] } else { Vec::new() };
            Ok((v, others))
        });
        self.pool.lock().expect("dataset pool").push(ds);
        let (mut v, others) = read.map_err(|e| {
            // The raster's size said: a forged header fails here, not when it was opened.
            format!(
                "{shown} ({w} x {h} samples): reading samples {x0}..={x1} x {z0}..={z1}: {}",
                gdal_message(&shown, e)
            )
        })?;
        for other in &others {
            if let Some(i) = (0..v.len()).find(|&i| v[i] != other[i]) {
                return Err(format!(
                    "{shown}: colour image (channels differ at file column {}, row {}): a height map must be grayscale or have equal R, G, B",
                    fx + i % nx,
                    fz + i / nx
                ));
            }
        }
        if self.flip[0] {
            v.chunks_mut(nx).for_each(|r| r.reverse());
        }
        if self.flip[1] {
            v = v.chunks(nx).rev().flatten().copied().collect();
        }
        for (i, s) in v.iter_mut().enumerate() {
            let void = match self.nodata {
                Some(nd) if nd.is_nan() => s.is_nan(),
                Some(nd) => *s == nd as f32,
                None => false,
            };
            if void || !s.is_finite() {
                return Err(format!(
                    "{shown}: sample at column {}, row {} is {}: read window by window (inputs over 8193 x 8193 samples or \
                     32769 a side, or --windows), voids (nodata) cannot be filled: fill them first (gdal_fillnodata), \
                     or prepare an input that is read whole",
                    x0 + i % nx,
                    z0 + i / nx,
                    if void { "a void (nodata)".to_string() } else { s.to_string() }
                ));
            }
            *s += self.raw_offset;
        }
        Ok(v)
    }
}

/// World x runs east and z south (SPEC section 1): a raster whose columns run west or
/// whose rows run north (a negative x step, a positive y step) is mirrored into that
/// order, its transform with it, and says so. A mirrored terrain would otherwise be drawn
/// with its handedness flipped, silently.
pub fn orient_east_and_south(r: &mut Raster) {
    let Some(t) = r.transform.as_mut() else { return };
    if t[2] != 0.0 || t[4] != 0.0 {
        return; // rotated: refused when the scale is decided
    }
    let (w, h) = (r.width, r.height);
    if t[1] < 0.0 {
        for row in r.samples.chunks_mut(w) {
            row.reverse();
        }
        t[0] += w as f64 * t[1];
        t[1] = -t[1];
        r.notes.push("columns run west in the file: mirrored so that x runs east".into());
    }
    if t[5] > 0.0 {
        let rows: Vec<Vec<f32>> = r.samples.chunks(w).rev().map(|c| c.to_vec()).collect();
        r.samples = rows.concat();
        t[3] += h as f64 * t[5];
        t[5] = -t[5];
        r.notes.push("rows run north in the file (south-up): mirrored so that z runs south".into());
    }
}

/// Prime-vertical and meridional radii of curvature at latitude `phi` (radians) on an
/// ellipsoid of semi-major axis `a` and first eccentricity squared `e2`.
pub fn radii(a: f64, e2: f64, phi: f64) -> (f64, f64) {
    let w = 1.0 - e2 * phi.sin().powi(2);
    (a / w.sqrt(), a * (1.0 - e2) / w.powf(1.5))
}

/// Metres per sample of a geographic raster at its centre latitude, and the worst
/// relative stretch of that one spacing per axis over the extent.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct GeographicFrame {
    pub spacing_m: [f64; 2],
    pub centre: [f64; 2],
    pub worst_stretch: f64,
}

/// Semi-major and semi-minor axes of the CRS's ellipsoid (WGS 84's when it names none).
fn ellipsoid(srs: &SpatialRef) -> (f64, f64) {
    (srs.semi_major().unwrap_or(6_378_137.0), srs.semi_minor().unwrap_or(6_356_752.314_245))
}

/// [`GeographicFrame`] from the raster's transform (degrees, or the CRS's angular unit),
/// size and ellipsoid.
pub fn geographic_frame(t: &[f64; 6], w: usize, h: usize, srs: &SpatialRef) -> GeographicFrame {
    let (a, b) = ellipsoid(srs);
    let rad = srs.angular_units();
    let rad = if rad > 0.0 { rad } else { std::f64::consts::PI / 180.0 };
    frame_on_ellipsoid(t, w, h, a, 1.0 - (b / a).powi(2), rad)
}

/// The pure part of [`geographic_frame`].
pub fn frame_on_ellipsoid(t: &[f64; 6], w: usize, h: usize, a: f64, e2: f64, rad_per_unit: f64) -> GeographicFrame {
    let (dlon, dlat) = (t[1].abs() * rad_per_unit, t[5].abs() * rad_per_unit);
    // Latitudes of the first and last rows' sample centres, and the middle.
    let lat_first = (t[3] + 0.5 * t[5]) * rad_per_unit;
    let lat_last = (t[3] + (h as f64 - 0.5) * t[5]) * rad_per_unit;
    let lon_centre = (t[0] + 0.5 * w as f64 * t[1]) * rad_per_unit;
    let phi_c = 0.5 * (lat_first + lat_last);
    let at = |phi: f64| {
        let (n, m) = radii(a, e2, phi);
        [n * phi.cos() * dlon, m * dlat]
    };
    let c = at(phi_c);
    let (lo, hi) = (lat_first.min(lat_last), lat_first.max(lat_last));
    let mut worst = 0.0f64;
    for phi in [lo, hi, 0.0f64.clamp(lo, hi)] {
        let s = at(phi);
        worst = worst.max((s[0] / c[0] - 1.0).abs()).max((s[1] / c[1] - 1.0).abs());
    }
    GeographicFrame { spacing_m: c, centre: [lon_centre.to_degrees(), phi_c.to_degrees()], worst_stretch: worst }
}

/// Warps a geographic raster too large for one spacing per axis to a transverse Mercator
/// projection centred on it, at its centre spacings; samples outside the source come
/// back as NaN (counted in `outside`, then filled as voids).
fn reproject(
    shown: &str,
    src: &Dataset,
    mut raster: Raster,
    srs: &SpatialRef,
    frame: &GeographicFrame,
) -> Result<Raster, HeightfieldError> {
    let bad = |m: String| HeightfieldError::invalid(shown, m);
    let (a, b) = ellipsoid(srs);
    let def = format!(
        "+proj=tmerc +lat_0={} +lon_0={} +k=1 +x_0=0 +y_0=0 +a={a} +b={b} +units=m +no_defs",
        frame.centre[1], frame.centre[0]
    );
    let mut dst_srs = SpatialRef::from_proj4(&def).map_err(|e| bad(format!("cannot make a local projection: {e}")))?;
    let mut src_srs = srs.clone();
    for s in [&mut dst_srs, &mut src_srs] {
        s.set_axis_mapping_strategy(gdal::spatial_ref::AxisMappingStrategy::TraditionalGisOrder);
    }
    let t = raster.transform.expect("geographic rasters have a transform");
    let (w, h) = (raster.width as f64, raster.height as f64);
    let bounds = [t[0], t[3] + h * t[5], t[0] + w * t[1], t[3]];
    let to = gdal::spatial_ref::CoordTransform::new(&src_srs, &dst_srs)
        .map_err(|e| bad(format!("cannot transform to the local projection: {e}")))?;
    let [x0, y0, x1, y1] = to
        .transform_bounds(
            &[bounds[0].min(bounds[2]), bounds[1].min(bounds[3]), bounds[0].max(bounds[2]), bounds[1].max(bounds[3])],
            21,
        )
        .map_err(|e| bad(format!("cannot transform the extent: {e}")))?;
    let [sx, sz] = frame.spacing_m;
    let (nw, nh) = (((x1 - x0) / sx).ceil() as usize, ((y1 - y0) / sz).ceil() as usize);
    if nw > MAX_SIDE || nh > MAX_SIDE {
        return Err(bad(format!("reprojected to {nw} x {nh} samples: larger than {MAX_SIDE} a side")));
    }
    let driver =
        gdal::DriverManager::get_driver_by_name("MEM").map_err(|e| bad(format!("GDAL has no MEM driver: {e}")))?;
    let mut dst = driver
        .create_with_band_type::<f32, _>("", nw, nh, 1)
        .map_err(|e| bad(format!("cannot allocate the reprojected raster: {e}")))?;
    dst.set_geo_transform(&[x0, sx, 0.0, y1, 0.0, -sz]).map_err(|e| bad(e.to_string()))?;
    dst.set_spatial_ref(&dst_srs).map_err(|e| bad(e.to_string()))?;
    {
        let mut band = dst.rasterband(1).map_err(|e| bad(e.to_string()))?;
        band.set_no_data_value(Some(f64::NAN)).map_err(|e| bad(e.to_string()))?;
        band.fill(f64::NAN, None).map_err(|e| bad(e.to_string()))?;
    }
    gdal::raster::reproject(src, &dst).map_err(|e| bad(format!("reprojection failed: {e}")))?;
    let band = dst.rasterband(1).map_err(|e| bad(e.to_string()))?;
    let samples =
        band.read_as::<f32>((0, 0), (nw, nh), (nw, nh), None).map_err(|e| bad(e.to_string()))?.into_shape_and_vec().1;
    // Which samples lie outside the source: their centres taken back to the source's CRS,
    // row by row. (The source's own voids come back as NaN too, GDAL skipping nodata,
    // but inside the footprint: they stay voids.)
    let back = gdal::spatial_ref::CoordTransform::new(&dst_srs, &src_srs)
        .map_err(|e| bad(format!("cannot transform back from the local projection: {e}")))?;
    let (lo_x, hi_x) = (bounds[0].min(bounds[2]), bounds[0].max(bounds[2]));
    let (lo_y, hi_y) = (bounds[1].min(bounds[3]), bounds[1].max(bounds[3]));
    let mut outside = vec![true; nw * nh];
    for j in 0..nh {
        let mut xs: Vec<f64> = (0..nw).map(|i| x0 + (i as f64 + 0.5) * sx).collect();
        let mut ys = vec![y1 - (j as f64 + 0.5) * sz; nw];
        if back.transform_coords(&mut xs, &mut ys, &mut []).is_ok() {
            for i in 0..nw {
                outside[j * nw + i] = !((lo_x..=hi_x).contains(&xs[i]) && (lo_y..=hi_y).contains(&ys[i]));
            }
        }
    }
    raster.outside = outside.iter().filter(|&&o| o).count();
    raster.outside_mask = Some(outside);
    raster.samples = samples;
    raster.width = nw;
    raster.height = nh;
    raster.format = HeightFormat::Float32;
    raster.transform = Some([x0, sx, 0.0, y1, 0.0, -sz]);
    raster.crs_wkt = dst_srs.to_wkt().ok();
    raster.crs_name = Some(def.replace(" +no_defs", ""));
    // NaN marks what has no data now; the file's own nodata (if any) is reported as read.
    raster.notes.push(format!(
        "reprojected to a local transverse Mercator projection centred at {:.4}, {:.4} (one spacing per axis would have been off by {:.1} %): {nw} x {nh} samples of {sx:.2} x {sz:.2} m",
        frame.centre[1], frame.centre[0], 100.0 * frame.worst_stretch
    ));
    raster.reprojected_nodata = raster.nodata;
    raster.nodata = Some(f64::NAN);
    Ok(raster)
}

/// An RGB(A) raster warped onto the terrain (SPEC section 9): texel `(i, j)` of the
/// result covers the terrain's true extent in equal steps from sample 0 to sample
/// `width - 1` (the shader's `uv = sample / (extent - 1)`), whatever the image's own CRS,
/// extent and resolution. `None` when the image or the terrain carries no georeferencing
/// (the image is then stretched over the terrain as it is). Where the image has no data,
/// texels are mid-grey.
pub fn drape(path: &Path, dem: &Georef, dem_size: (usize, usize)) -> Result<Option<(u32, u32, Vec<u8>)>, String> {
    init_gdal();
    let shown = path.display().to_string();
    if dem.wkt.is_empty() || dem.step == [0.0; 2] {
        return Ok(None);
    }
    let Ok(src) = Dataset::open(path) else { return Ok(None) };
    let (Ok(t), Ok(src_srs)) = (src.geo_transform(), src.spatial_ref()) else { return Ok(None) };
    let bands = src.raster_count();
    if !(3..=4).contains(&bands) {
        return Err(format!("{shown}: {bands} bands: a georeferenced texture needs red, green and blue"));
    }
    let mut dem_srs = SpatialRef::from_wkt(&dem.wkt).map_err(|e| format!("{shown}: the terrain's CRS: {e}"))?;
    let mut src_srs = src_srs;
    for s in [&mut dem_srs, &mut src_srs] {
        s.set_axis_mapping_strategy(gdal::spatial_ref::AxisMappingStrategy::TraditionalGisOrder);
    }
    // The terrain's extent in its CRS, sample centre 0 to sample centre (w - 1).
    let (w, h) = (dem_size.0 as f64, dem_size.1 as f64);
    let (x0, y0) = (dem.origin[0], dem.origin[1]);
    let (span_x, span_y) = ((w - 1.0) * dem.step[0], (h - 1.0) * dem.step[1]);
    // The image's resolution over that extent: its pixel size taken into the terrain's
    // CRS, at most 8192 texels a side.
    let (sw, sh) = src.raster_size();
    let to_dem = gdal::spatial_ref::CoordTransform::new(&src_srs, &dem_srs).map_err(|e| format!("{shown}: {e}"))?;
    let (ix0, ix1) = (t[0].min(t[0] + sw as f64 * t[1]), t[0].max(t[0] + sw as f64 * t[1]));
    let (iy0, iy1) = (t[3].min(t[3] + sh as f64 * t[5]), t[3].max(t[3] + sh as f64 * t[5]));
    let b = to_dem.transform_bounds(&[ix0, iy0, ix1, iy1], 21).map_err(|e| format!("{shown}: its extent: {e}"))?;
    let pixel = ((b[2] - b[0]) / sw as f64).min((b[3] - b[1]) / sh as f64).abs().max(f64::MIN_POSITIVE);
    let tw = ((span_x.abs() / pixel).round() as usize).clamp(1, 8192);
    let th = ((span_y.abs() / pixel).round() as usize).clamp(1, 8192);
    let driver = gdal::DriverManager::get_driver_by_name("MEM").map_err(|e| format!("GDAL: {e}"))?;
    let mut dst = driver.create_with_band_type::<u8, _>("", tw, th, 4).map_err(|e| format!("{shown}: {e}"))?;
    dst.set_geo_transform(&[x0, span_x / tw as f64, 0.0, y0, 0.0, span_y / th as f64]).map_err(|e| e.to_string())?;
    dst.set_spatial_ref(&dem_srs).map_err(|e| e.to_string())?;
    gdal::raster::reproject(&src, &dst).map_err(|e| format!("{shown}: warping onto the terrain failed: {e}"))?;
    let mut planes = Vec::with_capacity(4);
    for i in 1..=4 {
        let band = dst.rasterband(i).map_err(|e| e.to_string())?;
        planes.push(
            band.read_as::<u8>((0, 0), (tw, th), (tw, th), None).map_err(|e| e.to_string())?.into_shape_and_vec().1,
        );
    }
    // Where nothing was warped in (outside the image), GDAL leaves zeros in every band
    // of a 3-band source: the alpha band the warper fills tells; a 4-band source brings
    // its own alpha.
    let covered: Vec<bool> = if bands == 3 {
        (0..tw * th).map(|i| planes[0][i] != 0 || planes[1][i] != 0 || planes[2][i] != 0).collect()
    } else {
        planes[3].iter().map(|&a| a != 0).collect()
    };
    let mut rgba = Vec::with_capacity(tw * th * 4);
    for (i, &cov) in covered.iter().enumerate() {
        if cov {
            rgba.extend_from_slice(&[planes[0][i], planes[1][i], planes[2][i], 255]);
        } else {
            rgba.extend_from_slice(&[128, 128, 128, 255]);
        }
    }
    Ok(Some((tw as u32, th as u32, rgba)))
}

/// What the user declared about a terrain (`--spacing`, `--height-scale`, `--heights`),
/// overriding what the file says or the defaults assumed without it.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct Declared {
    pub spacing: Option<Spacing>,
    pub height_scale: Option<f32>,
    pub heights: Option<Heights>,
}

/// The vertical datum of a terrain's heights.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, clap::ValueEnum, serde::Serialize)]
#[serde(rename_all = "lowercase")]
pub enum Heights {
    /// Metres above sea level: water at or below 0 m, colours by absolute height.
    Absolute,
    /// Only relative: the lowest ground is shaded as water, colours span the range.
    #[default]
    Relative,
}

impl Heights {
    pub fn of(absolute: bool) -> Heights {
        if absolute {
            Heights::Absolute
        } else {
            Heights::Relative
        }
    }
}

/// Drops from the notes of a terrain whose frame was decided before (an archive's, by
/// `prepare`) those about what `declared` now sets: a spacing, height unit or datum the
/// options give is no longer assumed, nor what the archive said. The notes are the ones
/// [`decide`] writes, each naming the flag that sets what it is about.
pub fn drop_overridden(notes: &mut Vec<String>, declared: &Declared) {
    let set = [
        (declared.spacing.is_some(), "--spacing"),
        (declared.height_scale.is_some(), "--height-scale"),
        (declared.heights.is_some(), "--heights"),
    ];
    notes.retain(|n| !set.iter().any(|&(given, flag)| given && n.contains(flag)));
}

/// Applies `--heights` to a terrain whose datum was decided before (an archive's): the
/// note to print when it changes what the terrain said.
pub fn declare_heights(g: &mut crate::lod::heightfield::Georef, heights: Heights) -> Option<String> {
    let absolute = heights == Heights::Absolute;
    (g.absolute_heights != absolute).then(|| {
        g.absolute_heights = absolute;
        format!(
            "heights are {} from --heights, not as the archive says",
            if absolute { "metres above sea level" } else { "relative" }
        )
    })
}

/// What the loader decided, from the file and the options.
#[derive(Clone, Debug)]
pub struct Scale {
    pub spacing: Spacing,
    pub height_scale: f32,
    pub georef: Georef,
}

/// Decides spacing and height scale for `raster`: `--spacing` / `--height-scale` when
/// given (said in a note), else what the file says, else the defaults of a data set we
/// know by its contents (`known`), else assumed values, said loudly.
pub fn decide(
    shown: &str,
    raster: &Raster,
    declared: &Declared,
    known: Option<&KnownDataset>,
    outside_holes: bool,
) -> Result<Scale, HeightfieldError> {
    let Declared { spacing, height_scale, heights } = *declared;
    let bad = |m: String| HeightfieldError::invalid(shown, m);
    let mut g = Georef::default();
    let mut notes = Vec::new();
    let srs = raster.crs_wkt.as_deref().and_then(|w| SpatialRef::from_wkt(w).ok());
    // Spacing the file implies, with the words that say where it came from.
    let from_file: Option<(Spacing, String)> = match (&raster.transform, &srs) {
        (Some(t), _) if t[2] != 0.0 || t[4] != 0.0 => {
            return Err(bad(format!(
                "the raster is rotated or sheared (geotransform {t:?}): warp it north-up first (gdalwarp)"
            )))
        }
        (Some(t), Some(s)) => {
            g.crs = Some(raster.crs_name.clone().unwrap_or_else(|| crs_label(s)));
            g.wkt = raster.crs_wkt.clone().unwrap_or_default();
            g.origin = [t[0] + 0.5 * t[1], t[3] + 0.5 * t[5]];
            g.step = [t[1], t[5]];
            if s.is_geographic() {
                g.geographic = true;
                let f = geographic_frame(t, raster.width, raster.height, s);
                g.worst_stretch = f.worst_stretch;
                let sp = Spacing { x: f.spacing_m[0] as f32, z: f.spacing_m[1] as f32 };
                let words = format!(
                    "{:.6} x {:.6} degrees a sample at {:.4} {} -> {:.2} x {:.2} m (one spacing per axis is off by at most {:.2} % over the extent)",
                    t[1].abs(),
                    t[5].abs(),
                    f.centre[1].abs(),
                    if f.centre[1] >= 0.0 { "N" } else { "S" },
                    sp.x,
                    sp.z,
                    100.0 * f.worst_stretch
                );
                Some((sp, words))
            } else {
                let unit = s.linear_units();
                let unit = if unit > 0.0 { unit } else { 1.0 };
                let sp = Spacing { x: (t[1].abs() * unit) as f32, z: (t[5].abs() * unit) as f32 };
                let uname = s.linear_units_name().unwrap_or_else(|| "unit".into());
                Some((sp, format!("{} x {} {uname} a sample -> {:.3} x {:.3} m", t[1].abs(), t[5].abs(), sp.x, sp.z)))
            }
        }
        (Some(t), None) => {
            // A geotransform without a CRS: the pixel size is in unknown units. Degrees
            // look like a small pixel at a place on the globe.
            let on_globe = (-180.0..=360.0).contains(&t[0]) && (-90.0..=90.0).contains(&t[3]);
            let from = &raster.transform_from;
            let no_crs = if from.starts_with("the world file") {
                "no CRS (no .prj beside it)"
            } else if from == "the GeoTIFF tags" {
                "no CRS (its GeoKeys name none)"
            } else {
                "no CRS"
            };
            if spacing.is_none() && (t[1].abs() < 0.01 || (on_globe && t[1].abs() < 1.0)) {
                return Err(bad(format!(
                    "{from} give {} units per sample but {no_crs} says what a unit is (degrees?): \
                     give --spacing (or a .prj naming the CRS)",
                    t[1].abs()
                )));
            }
            g.origin = [t[0] + 0.5 * t[1], t[3] + 0.5 * t[5]];
            g.step = [t[1], t[5]];
            let sp = Spacing { x: t[1].abs() as f32, z: t[5].abs() as f32 };
            Some((
                sp,
                format!(
                    "{} x {} a sample from {from}; WARNING: {no_crs}, so its unit is ASSUMED to be the metre; \
                     give --spacing to set it",
                    t[1].abs(),
                    t[5].abs()
                ),
            ))
        }
        (None, _) => None,
    };
    notes.extend(raster.notes.iter().cloned());
    if raster.outside > 0 {
        notes.push(format!(
            "{} samples of the reprojected grid lie outside the source: {}",
            raster.outside,
            if outside_holes {
                "drawn as holes (filled only for the LOD bound)"
            } else {
                "filled from the nearest data and drawn (an archive keeps them with --voids hole)"
            }
        ));
    }
    let spacing = match (spacing, &from_file, known) {
        (Some(s), Some((_, words)), _) => {
            notes.push(format!("spacing {} x {} m from --spacing (the file says {words})", s.x, s.z));
            s
        }
        (Some(s), None, _) => {
            notes.push(format!("spacing {} x {} m from --spacing", s.x, s.z));
            s
        }
        (None, Some((s, words)), _) => {
            notes.push(format!("spacing: {words}"));
            *s
        }
        (None, None, Some(k)) => {
            notes
                .push(format!("not georeferenced; known data set {} by its contents: spacing {} m", k.name, k.spacing));
            Spacing::from(k.spacing)
        }
        (None, None, None) => {
            let s = 30.0;
            notes.push(format!(
                "WARNING: not georeferenced (no CRS, geotransform or world file): spacing {s} m ASSUMED; give --spacing"
            ));
            Spacing::from(s)
        }
    };
    // Height scale: the file's scale times its unit, else the known data set's, else
    // metres for georeferenced files, else a default by bit depth.
    let file_scale = raster.scale.unwrap_or(1.0);
    let georeferenced = g.crs.is_some();
    let file_height: Option<(f64, String)> = match &raster.vertical_unit {
        Some((m, name)) => Some((file_scale * m, format!("{file_scale} {name} a unit"))),
        None if raster.scale.is_some() => Some((
            file_scale,
            format!("scale {file_scale} a unit, unit not given: metres assumed (--height-scale sets it)"),
        )),
        None if georeferenced => Some((1.0, "unit not given: metres assumed".into())),
        None => None,
    };
    let height_scale = match (height_scale, &file_height, known) {
        (Some(v), Some((_, words)), _) => {
            notes.push(format!("height scale {v} m a unit from --height-scale (the file says {words})"));
            v
        }
        (Some(v), None, _) => {
            notes.push(format!("height scale {v} m a unit from --height-scale"));
            v
        }
        (None, Some((v, words)), _) => {
            // What was assumed names the flag that sets it.
            let sets = if words.contains("assumed") { " (--height-scale sets it)" } else { "" };
            notes.push(format!("heights: {words} -> {v} m a unit{sets}"));
            *v as f32
        }
        (None, None, Some(k)) => {
            notes.push(format!("heights: {} m a unit (known data set {})", k.height_scale, k.name));
            k.height_scale
        }
        (None, None, None) => {
            let v = match (raster.format, raster.bits) {
                (HeightFormat::Float32, _) => 1.0,
                (_, 8) => 8.0,
                _ => 0.1,
            };
            notes.push(format!("WARNING: height unit not given: {v} m a unit ASSUMED; give --height-scale"));
            v
        }
    };
    if let Some(o) = raster.offset {
        notes.push(format!("band offset {o} (in the height unit) added to every sample"));
    }
    if let Some(nd) = if raster.outside_mask.is_some() { raster.reprojected_nodata } else { raster.nodata } {
        notes.push(format!("nodata {nd}"));
    }
    let (absolute, why) = match heights {
        Some(h) => (h == Heights::Absolute, " (from --heights)"),
        None if georeferenced => (true, " (the file names its CRS)"),
        None => match known {
            Some(k) => (k.absolute, " (known data set)"),
            None => (false, ""),
        },
    };
    g.absolute_heights = absolute;
    notes.push(match (absolute, heights.is_some() || known.is_some()) {
        (true, _) => {
            format!("heights are metres above sea level{why}: water at or below 0 m, colours by absolute height")
        }
        (false, true) => {
            format!("heights are relative{why}: the lowest ground is shaded as water, colours span the range")
        }
        (false, false) => {
            "WARNING: heights ASSUMED relative (no CRS says they are metres above sea level): the lowest \
                           ground is shaded as water, colours span the range; give --heights absolute if they are \
                           metres above sea level"
                .into()
        }
    });
    g.notes = notes;
    Ok(Scale { spacing, height_scale, georef: g })
}

/// A data set from `shared/data` that carries no georeferencing, recognised by the
/// SHA-256 of its bytes (not its name: a renamed copy keeps its scale), with the scale
/// its publisher documents.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct KnownDataset {
    pub name: &'static str,
    pub sha256: &'static str,
    pub spacing: f32,
    pub height_scale: f32,
    /// Heights are metres above sea level (0 is the sea), not relative.
    pub absolute: bool,
}

pub const KNOWN: &[KnownDataset] = &[
    KnownDataset {
        name: "Puget Sound 1k (16-bit PNG)",
        sha256: "80229c93fb119e579fb440fe5bcd9cf7d8290681a80136840b938f7f1a6ebfea",
        spacing: 160.0,
        height_scale: 0.1,
        absolute: true,
    },
    KnownDataset {
        // One unit is about 25.7 m (h16 / 257 * 0.1 m).
        name: "Puget Sound 4k (8-bit JPEG)",
        sha256: "50b4f2d90a39b4ee2eca1abd3a2f18f48b64b1e171724a41613ff0aa46a06c10",
        spacing: 40.0,
        height_scale: 25.7,
        absolute: true,
    },
    KnownDataset {
        name: "Grand Canyon 4k x 2k (8-bit PNG)",
        sha256: "7eda80965b3a4cab6c60d8598598e2c79602c3c525b6c2683dad92721fffbe2b",
        spacing: 60.0,
        height_scale: 10.0,
        // Values 13..187 of 10 m: 130-1870 m, far below the real canyon's 700-2800 m.
        absolute: false,
    },
];

/// The known data set the file at `path` is, if it carries no georeferencing of its own
/// (only such files are looked up: their scale is documented beside them, not in them).
/// Files larger than every known one are not read.
pub fn known_for_file(
    shown: &str,
    path: &std::path::Path,
    raster: &Raster,
) -> Result<Option<&'static KnownDataset>, HeightfieldError> {
    const LARGEST_KNOWN_BYTES: u64 = 64 << 20;
    if raster.transform.is_some() || raster.crs_wkt.is_some() {
        return Ok(None);
    }
    let io = |source| HeightfieldError::Io { path: shown.to_string(), source };
    if std::fs::metadata(path).map_err(io)?.len() > LARGEST_KNOWN_BYTES {
        return Ok(None);
    }
    Ok(known_dataset(&std::fs::read(path).map_err(io)?))
}

/// The known data set whose bytes are `bytes`, if any.
pub fn known_dataset(bytes: &[u8]) -> Option<&'static KnownDataset> {
    use sha2::Digest;
    let digest = sha2::Sha256::digest(bytes);
    let hex: String = digest.iter().map(|b| format!("{b:02x}")).collect();
    KNOWN.iter().find(|k| k.sha256 == hex)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Against published values: at 46.5 N on WGS 84, 3 arc-seconds are about 64.0 m
    /// east-west and 92.6 m north-south; at the equator 92.8 m and 92.1 m.
    #[test]
    fn srtm_spacing_on_wgs84() {
        let (a, f) = (6_378_137.0, 1.0 / 298.257_223_563);
        let e2 = f * (2.0 - f);
        let d = 3.0 / 3600.0;
        let rainier = [-122.0 - d / 2.0, d, 0.0, 47.0 + d / 2.0, 0.0, -d];
        let fr = frame_on_ellipsoid(&rainier, 1201, 1201, a, e2, std::f64::consts::PI / 180.0);
        assert!((fr.centre[1] - 46.5).abs() < 1e-9, "{fr:?}");
        assert!((fr.spacing_m[0] - 64.0).abs() < 0.1, "{fr:?}");
        assert!((fr.spacing_m[1] - 92.6).abs() < 0.1, "{fr:?}");
        // cos varies by about 0.9 % over the tile at this latitude: just under the limit.
        assert!(fr.worst_stretch > 0.008 && fr.worst_stretch < MAX_STRETCH, "{fr:?}");
        let equator = [0.0, d, 0.0, 0.5, 0.0, -d];
        let fe = frame_on_ellipsoid(&equator, 1201, 1201, a, e2, std::f64::consts::PI / 180.0);
        assert!((fe.spacing_m[0] - 92.77).abs() < 0.05 && (fe.spacing_m[1] - 92.12).abs() < 0.05, "{fe:?}");
        // Ten degrees tall at 50 N: far over the limit.
        let tall = [0.0, 0.01, 0.0, 55.0, 0.0, -0.01];
        assert!(frame_on_ellipsoid(&tall, 100, 1000, a, e2, std::f64::consts::PI / 180.0).worst_stretch > 0.05);
    }

    #[test]
    fn unit_names() {
        assert_eq!(metres_per_unit("ft"), Some(0.3048));
        assert_eq!(metres_per_unit("metre"), Some(1.0));
        assert!((metres_per_unit("US survey foot").unwrap() - 0.3048006).abs() < 1e-6);
        assert_eq!(metres_per_unit("furlong"), None);
    }
}
