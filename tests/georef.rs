//! Georeferencing is read from the file (SPEC section 9): the SRTM tiles' degrees become
//! metres per axis on WGS 84, a projected GeoTIFF written here with known tags loads at
//! its own scale and units, a world file places a PNG, a renamed copy of a known data set
//! keeps its scale, options override and say so, and a geographic raster too tall for
//! one spacing per axis is reprojected.

mod common;
use common::{data, TempDir};
use std::path::Path;
use tiff::encoder::{colortype, TiffEncoder};
use tiff::tags::Tag;
use vkterrain::input::load::{load, LoadOptions};
use vkterrain::lod::heightfield::{Heightfield, Spacing};

fn load_default(p: &Path) -> Heightfield {
    load(p, &LoadOptions::default()).unwrap_or_else(|e| panic!("{e}"))
}

/// Metres per degree of longitude and latitude at `lat` on WGS 84, written out from the
/// ellipsoid's definition (not the loader's code): the parallel's radius over 360
/// degrees and the meridian's radius of curvature.
fn wgs84_metres_per_degree(lat: f64) -> (f64, f64) {
    let a = 6_378_137.0f64;
    let f = 1.0 / 298.257_223_563;
    let e2 = 2.0 * f - f * f;
    let s = lat.to_radians().sin();
    let parallel = a * lat.to_radians().cos() / (1.0 - e2 * s * s).sqrt();
    let meridian = a * (1.0 - e2) / (1.0 - e2 * s * s).powf(1.5);
    (parallel * std::f64::consts::PI / 180.0, meridian * std::f64::consts::PI / 180.0)
}

#[test]
fn srtm_tiles_are_metres_per_axis_on_wgs84() {
    for (name, centre_lat) in [("mt_rainier_90m.tif", 46.5), ("mt_fuji_90m.tif", 35.5), ("mt_everest_90m.tif", 27.5)] {
        let hf = load_default(&data(&format!("srtm3/{name}")));
        let (ex, ez) = wgs84_metres_per_degree(centre_lat);
        let (ex, ez) = (ex * 3.0 / 3600.0, ez * 3.0 / 3600.0);
        let (sx, sz) = (hf.spacing.x as f64, hf.spacing.z as f64);
        assert!(
            (sx / ex - 1.0).abs() < 0.005 && (sz / ez - 1.0).abs() < 0.005,
            "{name}: {sx} x {sz}, want {ex} x {ez}"
        );
        assert_eq!(hf.georef.crs.as_deref(), Some("EPSG:4326"), "{name}");
        assert!(hf.georef.geographic);
        assert_eq!(hf.height_scale, 1.0, "{name}: SRTM heights are metres");
        assert!(hf.georef.worst_stretch < 0.01, "{name}: {}", hf.georef.worst_stretch);
    }
    // The figures for Rainier: about 64.0 m east-west by 92.6 m north-south.
    let r = load_default(&data("srtm3/mt_rainier_90m.tif"));
    assert!((r.spacing.x - 64.0).abs() < 0.1 && (r.spacing.z - 92.6).abs() < 0.1, "{:?}", r.spacing);
    // The first sample's centre: the tie point (upper-left corner) plus half a sample.
    let d = 3.0 / 3600.0;
    assert!((r.georef.origin[0] - (-122.000417 + d / 2.0)).abs() < 1e-5, "{:?}", r.georef.origin);
    assert!((r.georef.origin[1] - (47.000417 - d / 2.0)).abs() < 1e-5, "{:?}", r.georef.origin);
}

/// GeoKey directory entries (key, value), all stored inline (SHORT values).
fn geokeys(keys: &[(u16, u16)]) -> Vec<u16> {
    let mut v = vec![1, 1, 0, keys.len() as u16];
    for &(k, val) in keys {
        v.extend([k, 0, 1, val]);
    }
    v
}

/// A GeoTIFF of `w x h` float samples with the given tags, written with the `tiff`
/// crate (not GDAL, so that the reader is checked against the tags themselves).
fn write_geotiff(
    path: &Path,
    (w, h): (u32, u32),
    samples: &[f32],
    pixel: [f64; 2],
    tie: [f64; 2],
    keys: &[(u16, u16)],
    nodata: Option<&str>,
) {
    let file = std::fs::File::create(path).unwrap();
    let mut enc = TiffEncoder::new(file).unwrap();
    let mut img = enc.new_image::<colortype::Gray32Float>(w, h).unwrap();
    img.encoder().write_tag(Tag::Unknown(33550), &[pixel[0], pixel[1], 0.0][..]).unwrap();
    img.encoder().write_tag(Tag::Unknown(33922), &[0.0, 0.0, 0.0, tie[0], tie[1], 0.0][..]).unwrap();
    img.encoder().write_tag(Tag::Unknown(34735), &geokeys(keys)[..]).unwrap();
    if let Some(nd) = nodata {
        img.encoder().write_tag(Tag::Unknown(42113), nd).unwrap();
    }
    img.write_data(samples).unwrap();
}

/// UTM zone 10N, 25 m pixels, heights in international feet, nodata -9999: loads at
/// 25 m, 0.3048 m a unit, the voids filled and counted, the origin at the first
/// sample's centre.
#[test]
fn projected_geotiff_loads_at_its_own_scale() {
    let dir = TempDir::new("georef");
    let path = dir.path().join("utm_feet.tif");
    let (w, h) = (65u32, 49u32);
    let mut s: Vec<f32> = (0..w * h).map(|i| 1000.0 + (i % w) as f32 * 3.0 + (i / w) as f32).collect();
    for i in [5 * w + 7, 20 * w + 30, 20 * w + 31] {
        s[i as usize] = -9999.0;
    }
    let keys = [(1024, 1), (1025, 1), (3072, 32610), (4096, 8228), (4099, 9002)];
    write_geotiff(&path, (w, h), &s, [25.0, 25.0], [500_000.0, 5_200_000.0], &keys, Some("-9999"));
    let hf = load_default(&path);
    assert_eq!(hf.spacing, Spacing { x: 25.0, z: 25.0 });
    assert!((hf.height_scale - 0.3048).abs() < 1e-6, "height scale {} (feet are 0.3048 m)", hf.height_scale);
    assert_eq!(hf.void_samples, 3);
    assert_eq!(
        hf.georef.crs.as_deref().map(|c| c.starts_with("EPSG:32610") || c.contains("UTM zone 10N")),
        Some(true),
        "{:?}",
        hf.georef.crs
    );
    assert_eq!(hf.georef.origin, [500_012.5, 5_199_987.5]);
    assert!(!hf.georef.geographic);
    // The filled samples lie between their neighbours (a plane is its own fill).
    assert!((hf.raw_at(7, 5) - (1000.0 + 21.0 + 5.0)).abs() < 0.01, "{}", hf.raw_at(7, 5));

    // Options override, and the note says what the file said.
    let o = LoadOptions { spacing: Some(Spacing { x: 10.0, z: 12.0 }), height_scale: Some(1.0), ..Default::default() };
    let hf = load(&path, &o).unwrap();
    assert_eq!((hf.spacing, hf.height_scale), (Spacing { x: 10.0, z: 12.0 }, 1.0));
    let notes = hf.georef.notes.join("\n");
    assert!(notes.contains("--spacing") && notes.contains("25 x 25"), "{notes}");
    assert!(notes.contains("--height-scale") && notes.contains("foot"), "{notes}");
}

/// Non-square pixels in a projected CRS: the spacing differs per axis.
#[test]
fn non_square_pixels_give_two_spacings() {
    let dir = TempDir::new("georef");
    let path = dir.path().join("rect.tif");
    let s = vec![10.0f32; 17 * 9];
    write_geotiff(
        &path,
        (17, 9),
        &s,
        [2.0, 5.0],
        [300_000.0, 4_000_000.0],
        &[(1024, 1), (1025, 1), (3072, 32633)],
        None,
    );
    let hf = load_default(&path);
    assert_eq!(hf.spacing, Spacing { x: 2.0, z: 5.0 });
    assert_eq!(hf.height_scale, 1.0);
}

/// A PNG with a world file: placed by it (units taken as metres without a CRS, and said);
/// a world file in degrees without a CRS is refused rather than drawn a million times
/// too small.
#[test]
fn world_files_place_pngs() {
    let dir = TempDir::new("georef");
    let png = dir.path().join("hill.png");
    image::ImageBuffer::<image::Luma<u16>, _>::from_fn(33, 17, |x, y| image::Luma([(x * 100 + y) as u16]))
        .save(&png)
        .unwrap();
    std::fs::write(dir.path().join("hill.pgw"), "7.5\n0\n0\n-7.5\n1000.0\n2000.0\n").unwrap();
    let hf = load_default(&png);
    assert_eq!(hf.spacing, Spacing::from(7.5));
    assert_eq!(hf.georef.origin, [1000.0, 2000.0]);
    assert!(hf.georef.notes.join(" ").contains("world file"), "{:?}", hf.georef.notes);
    std::fs::write(dir.path().join("hill.pgw"), "0.000833333\n0\n0\n-0.000833333\n-122.0\n47.0\n").unwrap();
    let e = load(&png, &LoadOptions::default()).unwrap_err().to_string();
    assert!(e.contains("hill.png") && e.contains("no CRS"), "{e}");
}

/// A copy of Puget Sound 1k under another name keeps its documented scale (the scale came
/// from the file name once: 160 m became 30 m on renaming).
#[test]
fn a_renamed_known_data_set_keeps_its_scale() {
    let dir = TempDir::new("georef");
    let copy = dir.path().join("my_terrain.png");
    std::fs::copy(data("puget_sound/ps_height_1k.png"), &copy).unwrap();
    let hf = load_default(&copy);
    assert_eq!((hf.spacing, hf.height_scale), (Spacing::from(160.0), 0.1));
    // An unknown file without georeferencing gets assumed values, said as a warning.
    let other = dir.path().join("unknown.png");
    image::ImageBuffer::<image::Luma<u16>, _>::from_fn(9, 9, |x, y| image::Luma([(x + y) as u16]))
        .save(&other)
        .unwrap();
    let hf = load_default(&other);
    let notes = hf.georef.notes.join("\n");
    assert!(notes.contains("WARNING") && notes.contains("ASSUMED") && notes.contains("--spacing"), "{notes}");
    assert_eq!(hf.georef.crs, None);
}

/// A geographic raster 12 degrees tall at 50 N: one spacing per axis would be off by
/// 15 % at its edges, so it is warped to a local transverse Mercator projection; its
/// heights (a function of latitude) land where that projection puts their latitudes.
#[test]
fn tall_geographic_rasters_are_reprojected() {
    let dir = TempDir::new("georef");
    let path = dir.path().join("tall.tif");
    let (w, h) = (41u32, 241u32);
    let (top, step) = (56.0f64, 0.05f64);
    // Height = 100 m per degree of latitude above 40 N, at each sample's centre.
    let s: Vec<f32> = (0..w * h).map(|i| ((top - (i / w) as f64 * step - step / 2.0 - 40.0) * 100.0) as f32).collect();
    write_geotiff(&path, (w, h), &s, [step, step], [10.0, top], &[(1024, 2), (1025, 1), (2048, 4326)], None);
    let hf = load_default(&path);
    let notes = hf.georef.notes.join("\n");
    assert!(notes.contains("reprojected"), "{notes}");
    assert!(!hf.georef.geographic);
    // The local projection is named by its PROJ string, which says where it is.
    assert!(hf.georef.crs.as_deref().is_some_and(|c| c.starts_with("+proj=tmerc +lat_0=49.97")), "{:?}", hf.georef.crs);
    // What lies outside the source is drawn as a hole, not invented terrain; the file
    // had no voids of its own.
    let holes = hf.void_mask.as_ref().expect("the grid outside the source is a hole");
    assert!(holes.iter().any(|&h| h) && !holes.iter().all(|&h| h));
    assert_eq!(hf.void_samples, 0, "the file has no voids");
    // The centre spacings at 50 N: 0.05 degrees of longitude and latitude in metres.
    let (ex, ez) = wgs84_metres_per_degree(50.0);
    assert!((hf.spacing.x as f64 / (ex * step) - 1.0).abs() < 0.005, "{:?}", hf.spacing);
    assert!((hf.spacing.z as f64 / (ez * step) - 1.0).abs() < 0.005, "{:?}", hf.spacing);
    // Each sample's height is its latitude's: the georeferencing the loader reports
    // (origin and step in the local projection) transformed back to WGS 84 by PROJ.
    let mut local = gdal::spatial_ref::SpatialRef::from_wkt(&hf.georef.wkt).unwrap();
    let mut wgs84 = gdal::spatial_ref::SpatialRef::from_epsg(4326).unwrap();
    for s in [&mut local, &mut wgs84] {
        s.set_axis_mapping_strategy(gdal::spatial_ref::AxisMappingStrategy::TraditionalGisOrder);
    }
    let back = gdal::spatial_ref::CoordTransform::new(&local, &wgs84).unwrap();
    let mut checked = 0;
    for (x, z) in [(20, 120), (5, 30), (35, 200), (hf.width as i64 / 2, hf.height as i64 / 2)] {
        let mut e = [hf.georef.origin[0] + x as f64 * hf.georef.step[0]];
        let mut n = [hf.georef.origin[1] + z as f64 * hf.georef.step[1]];
        back.transform_coords(&mut e, &mut n, &mut []).unwrap();
        let (lon, lat) = (e[0], n[0]);
        if !(10.05..10.0 + w as f64 * step - 0.05).contains(&lon)
            || !(top - h as f64 * step + 0.05..top - 0.05).contains(&lat)
        {
            continue; // outside the source (filled like a void)
        }
        let want = (lat - 40.0) * 100.0;
        // Bilinear resampling of a function linear in latitude: exact but for the
        // curvature of parallels within one sample (well under a metre here).
        assert!(
            (hf.raw_at(x, z) as f64 - want).abs() < 0.5,
            "sample ({x}, {z}) at {lon:.4} E {lat:.4} N: {} for {want}",
            hf.raw_at(x, z)
        );
        checked += 1;
    }
    assert!(checked >= 3, "only {checked} samples inside the source");
}

/// The notes say what became of the samples outside a reprojected source: holes in
/// memory (above), filled and drawn in an archive prepared without `--voids hole`; `prepare`
/// says so and never that they are "drawn as holes".
#[test]
fn prepare_says_the_samples_outside_a_reprojected_source_are_filled() {
    let dir = TempDir::new("georef");
    let path = dir.path().join("tall.tif");
    let (w, h) = (41u32, 241u32);
    let s: Vec<f32> = (0..w * h).map(|i| (i / w) as f32).collect();
    write_geotiff(&path, (w, h), &s, [0.05, 0.05], [10.0, 56.0], &[(1024, 2), (1025, 1), (2048, 4326)], None);
    let notes = load_default(&path).georef.notes.join("\n");
    assert!(notes.contains("outside the source: drawn as holes"), "{notes}");
    let out = dir.path().join("tall.pmtiles");
    let o = common::cli(&["prepare", path.to_str().unwrap(), "--out", out.to_str().unwrap()]);
    let e = String::from_utf8_lossy(&o.stderr);
    assert!(o.status.success(), "{e}");
    assert!(e.contains("outside the source: filled from the nearest data and drawn"), "{e}");
    assert!(!e.contains("holes"), "{e}");
}

/// A georeferenced colour image drapes by its own georeferencing: an RGB GeoTIFF at 5 m
/// pixels, larger than the terrain and offset from it, with a red square at known UTM
/// coordinates, is warped onto a 10 m terrain so that the square's texels are where the
/// square is on the ground; a picture without georeferencing is stretched as before.
#[test]
fn georeferenced_textures_drape_by_their_coordinates() {
    let dir = TempDir::new("georef");
    let dem = dir.path().join("dem.tif");
    let s = vec![100.0f32; 65 * 65];
    write_geotiff(
        &dem,
        (65, 65),
        &s,
        [10.0, 10.0],
        [500_000.0, 5_200_000.0],
        &[(1024, 1), (1025, 1), (3072, 32610)],
        None,
    );
    let hf = load_default(&dem);
    let tex = dir.path().join("colour.tif");
    let red = |e: f64, n: f64| (500_200.0..500_300.0).contains(&e) && (5_199_700.0..5_199_800.0).contains(&n);
    let (tw, th) = (200u32, 200u32);
    let mut rgb = Vec::with_capacity((tw * th * 3) as usize);
    for row in 0..th {
        for col in 0..tw {
            let (e, n) = (499_900.0 + (col as f64 + 0.5) * 5.0, 5_200_100.0 - (row as f64 + 0.5) * 5.0);
            rgb.extend_from_slice(if red(e, n) { &[220, 20, 20] } else { &[20, 160, 40] });
        }
    }
    {
        let file = std::fs::File::create(&tex).unwrap();
        let mut enc = TiffEncoder::new(file).unwrap();
        let mut img = enc.new_image::<colortype::RGB8>(tw, th).unwrap();
        img.encoder().write_tag(Tag::Unknown(33550), &[5.0, 5.0, 0.0][..]).unwrap();
        img.encoder().write_tag(Tag::Unknown(33922), &[0.0, 0.0, 0.0, 499_900.0, 5_200_100.0, 0.0][..]).unwrap();
        img.encoder().write_tag(Tag::Unknown(34735), &geokeys(&[(1024, 1), (1025, 1), (3072, 32610)])[..]).unwrap();
        img.write_data(&rgb).unwrap();
    }
    let args =
        vkterrain::app::cli::TextureArgs { texture: Some(tex), detail: None, detail_tiling: 64.0, detail_weight: 0.7 };
    let t = args.load(&hf).unwrap().base.expect("a base texture");
    // The terrain spans 640 m from sample 0 to 64: 128 texels of 5 m.
    assert_eq!((t.width, t.height), (128, 128));
    let texel = |e: f64, n: f64| {
        let (i, j) = (((e - 500_005.0) / 5.0) as usize, ((5_199_995.0 - n) / 5.0) as usize);
        let k = (j * t.width as usize + i) * 4;
        [t.rgba[k], t.rgba[k + 1], t.rgba[k + 2]]
    };
    let mut checked = 0;
    for n in (5_199_400..5_199_990).step_by(15) {
        for e in (500_010..500_640).step_by(15) {
            let (e, n) = (e as f64, n as f64);
            // Clear of the square's edges, where the bilinear warp blends.
            let edge = [500_200.0, 500_300.0].iter().any(|v: &f64| (e - v).abs() < 8.0)
                || [5_199_700.0, 5_199_800.0].iter().any(|v: &f64| (n - v).abs() < 8.0);
            if edge {
                continue;
            }
            let c = texel(e, n);
            let is_red = c[0] > 150 && c[1] < 80;
            assert_eq!(is_red, red(e, n), "E {e} N {n}: texel {c:?}");
            checked += 1;
        }
    }
    assert!(checked > 1000, "{checked}");
    // Without georeferencing the picture is used as it is.
    let plain = dir.path().join("plain.png");
    image::RgbImage::from_pixel(7, 5, image::Rgb([1, 2, 3])).save(&plain).unwrap();
    let args = vkterrain::app::cli::TextureArgs {
        texture: Some(plain),
        detail: None,
        detail_tiling: 64.0,
        detail_weight: 0.7,
    };
    let t = args.load(&hf).unwrap().base.unwrap();
    assert_eq!((t.width, t.height, &t.rgba[..4]), (7, 5, &[1u8, 2, 3, 255][..]));
}

/// World x runs east and z south whatever the file's order: a south-up raster (rows
/// running north, by a ModelTransformation with a positive y step) and one whose columns
/// run west are mirrored at load, with a note; otherwise the terrain would be drawn with
/// its handedness flipped.
#[test]
fn south_up_and_west_running_rasters_are_mirrored() {
    let dir = TempDir::new("georef");
    let (w, h) = (65u32, 49u32);
    let s: Vec<f32> = (0..w * h).map(|i| ((i % w) + 100 * (i / w)) as f32).collect();
    for (name, (a, f)) in [("south_up.tif", (25.0, 35.0)), ("west.tif", (-25.0, -35.0))] {
        let path = dir.path().join(name);
        {
            let file = std::fs::File::create(&path).unwrap();
            let mut enc = TiffEncoder::new(file).unwrap();
            let mut img = enc.new_image::<colortype::Gray32Float>(w, h).unwrap();
            #[rustfmt::skip]
            let m = [a, 0.0, 0.0, 500_000.0, 0.0, f, 0.0, 5_200_000.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0];
            img.encoder().write_tag(Tag::Unknown(34264), &m[..]).unwrap();
            img.encoder().write_tag(Tag::Unknown(34735), &geokeys(&[(1024, 1), (1025, 1), (3072, 32610)])[..]).unwrap();
            img.write_data(&s).unwrap();
        }
        let hf = load_default(&path);
        let notes = hf.georef.notes.join("\n");
        assert_eq!(hf.spacing, Spacing { x: 25.0, z: 35.0 }, "{name}");
        assert!(hf.georef.step[0] > 0.0 && hf.georef.step[1] < 0.0, "{name}: {:?}", hf.georef.step);
        let (wl, hl) = (w as i64 - 1, h as i64 - 1);
        if name == "south_up.tif" {
            assert!(notes.contains("south-up"), "{notes}");
            // The file's last row is the northernmost: it comes first.
            assert_eq!(hf.raw_at(0, 0), (100 * hl) as f32);
            assert_eq!(hf.raw_at(wl, hl), wl as f32);
            // The first sample's centre: the north-west corner.
            assert_eq!(hf.georef.origin, [500_012.5, 5_200_000.0 + 35.0 * (h as f64 - 0.5)]);
        } else {
            assert!(notes.contains("run west"), "{notes}");
            // The file's last column is the westernmost.
            assert_eq!(hf.raw_at(0, 0), wl as f32);
            assert_eq!(hf.georef.origin, [500_000.0 - 25.0 * (w as f64 - 0.5), 5_200_000.0 - 17.5]);
        }
    }
}

/// Georeferencing that cannot be right is refused, naming the problem, and what was
/// assumed or added is said: a raster beyond the pole, a CRS with a zero pixel size, a
/// world file in degrees without a CRS; a metric world file without one gets a WARNING; a
/// `.prj` beside a PNG's world file gives its CRS (US survey feet); a band offset is said.
#[test]
fn broken_georeferencing_is_refused_and_assumptions_said() {
    let dir = TempDir::new("georef");
    let err = |p: &Path| load(p, &LoadOptions::default()).unwrap_err().to_string();
    let pole = dir.path().join("pole.tif");
    write_geotiff(&pole, (11, 11), &[1.0; 121], [1.0, 1.0], [0.0, 95.0], &[(1024, 2), (1025, 1), (2048, 4326)], None);
    let e = err(&pole);
    assert!(e.contains("pole.tif") && e.contains("beyond a pole"), "{e}");
    let zero = dir.path().join("zero.tif");
    write_geotiff(
        &zero,
        (9, 9),
        &[1.0; 81],
        [0.0, 30.0],
        [500_000.0, 5_200_000.0],
        &[(1024, 1), (1025, 1), (3072, 32610)],
        None,
    );
    let e = err(&zero);
    assert!(e.contains("zero.tif") && e.contains("geotransform"), "{e}");
    let png = dir.path().join("wf.png");
    image::ImageBuffer::<image::Luma<u16>, _>::from_fn(9, 9, |x, y| image::Luma([(x + y) as u16])).save(&png).unwrap();
    std::fs::write(dir.path().join("wf.pgw"), "0.01\n0\n0\n-0.01\n-122.0\n47.0\n").unwrap();
    let e = err(&png);
    assert!(e.contains("wf.png") && e.contains("degrees"), "{e}");
    std::fs::write(dir.path().join("wf.pgw"), "10\n0\n0\n-10\n600000.0\n4200000.0\n").unwrap();
    let hf = load_default(&png);
    let notes = hf.georef.notes.join("\n");
    assert!(notes.contains("WARNING") && notes.contains("ASSUMED"), "{notes}");
    let wkt = gdal::spatial_ref::SpatialRef::from_epsg(2227).unwrap().to_wkt().unwrap();
    std::fs::write(dir.path().join("wf.prj"), wkt).unwrap();
    let hf = load_default(&png);
    assert!((hf.spacing.x - 3.048006).abs() < 1e-5, "10 US survey feet: {:?}", hf.spacing);
    assert_eq!(hf.georef.crs.as_deref(), Some("EPSG:2227"));
}

/// A float DEM of bathymetry and topography with no georeferencing at all (44 % of its
/// samples below 0 m): every assumed value is warned with the flag that sets it, its
/// heights are ASSUMED relative (no water, colours over the range) until `--heights
/// absolute` declares them metres above sea level; then the sea is at 0 m, in the loader,
/// in `render`'s JSON and in the picture (water over the 44 % below 0 m).
#[test]
fn heights_can_be_declared_absolute_for_a_dem_without_georeferencing() {
    let dir = TempDir::new("heights");
    let path = dir.path().join("bathymetry.tif");
    let (w, h) = (129u32, 129u32);
    let height = |x: u32| -400.0 + x as f32 * 7.0; // below 0 m for x < 58: 44 %
    let s: Vec<f32> = (0..w * h).map(|i| height(i % w)).collect();
    {
        let file = std::fs::File::create(&path).unwrap();
        let mut enc = TiffEncoder::new(file).unwrap();
        enc.write_image::<colortype::Gray32Float>(w, h, &s).unwrap();
    }
    let below = s.iter().filter(|&&v| v <= 0.0).count() as f64 / s.len() as f64;
    assert!((0.43..0.46).contains(&below), "{below}");
    let hf = load_default(&path);
    let notes = hf.georef.notes.join("\n");
    assert!(!hf.georef.absolute_heights);
    for (assumed, flag) in
        [("spacing", "--spacing"), ("height unit", "--height-scale"), ("heights", "--heights absolute")]
    {
        let line = notes.lines().find(|l| l.contains("WARNING") && l.contains(assumed)).unwrap_or_else(|| {
            panic!("no WARNING about the assumed {assumed}: {notes}");
        });
        assert!(line.contains(flag), "the WARNING about {assumed} does not name {flag}: {line}");
    }
    let declared = LoadOptions {
        spacing: Some(Spacing::from(500.0)),
        height_scale: Some(1.0),
        heights: Some(vkterrain::input::georef::Heights::Absolute),
        ..Default::default()
    };
    let hf = load(&path, &declared).unwrap();
    assert!(hf.georef.absolute_heights);
    assert_eq!(hf.sea_level([-400.0, 496.0]), 0.0);
    let notes = hf.georef.notes.join("\n");
    assert!(notes.contains("metres above sea level (from --heights)"), "{notes}");
    assert!(!notes.lines().any(|l| l.contains("WARNING") && l.contains("heights")), "{notes}");
    // Drawn: from above the middle, the whole terrain in view.
    let water = |p: &image::Rgba<u8>| p[2] as i32 > p[0] as i32 + 40 && p[2] as i32 > p[1] as i32 + 15;
    let mut wet = Vec::new();
    for heights in ["absolute", "relative"] {
        let out = dir.path().join(format!("{heights}.png"));
        let o = common::cli(&[
            "render",
            path.to_str().unwrap(),
            "--spacing",
            "500",
            "--height-scale",
            "1",
            "--heights",
            heights,
            "--camera",
            "32000,90000,32100",
            "--look-at",
            "32000,0,32000",
            "--size",
            "160x120",
            "--sun",
            "off",
            "--validation",
            "on",
            "--out",
            out.to_str().unwrap(),
        ]);
        assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
        let r: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
        assert_eq!(r["heights"], heights, "{r}");
        let img = image::open(&out).unwrap().to_rgba8();
        let share = img.pixels().filter(|p| water(p)).count() as f64 / img.pixels().count() as f64;
        wet.push(share);
    }
    // From 90 km up at 60 degrees the frame spans 104 x 139 km: the 64 km square fills
    // 28 % of it, and its 44 % below 0 m 12.5 % of the pixels when 0 m is the sea; next to
    // none when the lowest ground is.
    assert!((0.10..0.16).contains(&wet[0]), "absolute: water on {:.1} % of the pixels", 100.0 * wet[0]);
    assert!(wet[1] < 0.02, "relative: water on {:.1} % of the pixels", 100.0 * wet[1]);
    // Prepared into an archive, it says what was assumed wherever it is opened, streamed
    // too; what the options now set is no longer said to be assumed.
    let archive = dir.path().join("bathymetry.pmtiles");
    let a = archive.to_str().unwrap();
    let o = common::cli(&["prepare", path.to_str().unwrap(), "--out", a]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let o = common::cli(&["stream", a, "--frames", "2", "--fps", "300"]);
    let e = String::from_utf8_lossy(&o.stderr);
    assert!(o.status.success(), "{e}");
    assert!(e.lines().any(|l| l.contains("WARNING") && l.contains("--heights absolute")), "{e}");
    assert!(e.lines().any(|l| l.contains("WARNING") && l.contains("--spacing")), "{e}");
    let out = dir.path().join("archive.png");
    let o = common::cli(&[
        "render",
        a,
        "--spacing",
        "500",
        "--height-scale",
        "1",
        "--heights",
        "absolute",
        "--size",
        "64x48",
        "--out",
        out.to_str().unwrap(),
    ]);
    let e = String::from_utf8_lossy(&o.stderr);
    assert!(o.status.success(), "{e}");
    assert!(!e.contains("ASSUMED"), "declared, yet said to be assumed: {e}");
    let r: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    assert_eq!(r["heights"], "absolute", "{r}");
    // The flight takes the same declarations; an archive prepared again with them records
    // them, and no longer says they were assumed.
    let declared = ["--spacing", "500", "--height-scale", "1", "--heights", "absolute"];
    let o = common::cli(&[&["stream", a, "--frames", "2", "--fps", "300"][..], &declared].concat());
    let e = String::from_utf8_lossy(&o.stderr);
    assert!(o.status.success(), "{e}");
    assert!(!e.contains("ASSUMED"), "declared, yet said to be assumed: {e}");
    let r = common::json_in(&String::from_utf8_lossy(&o.stdout));
    assert_eq!((r["heights"].as_str(), r["spacing_m"].clone()), (Some("absolute"), serde_json::json!([500.0, 500.0])));
    let again = dir.path().join("again.pmtiles");
    let o = common::cli(&[&["prepare", a, "--out", again.to_str().unwrap()][..], &declared].concat());
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let o = common::cli(&["stream", again.to_str().unwrap(), "--frames", "2", "--fps", "300"]);
    let e = String::from_utf8_lossy(&o.stderr);
    assert!(o.status.success(), "{e}");
    assert!(!e.contains("ASSUMED"), "prepared with the declarations, yet said to be assumed: {e}");
    assert_eq!(common::json_in(&String::from_utf8_lossy(&o.stdout))["heights"], "absolute");
}

/// A GeoTIFF with a geotransform (25 m pixels) and no CRS: its note speaks of the
/// GeoTIFF's tags (not of a world file or a missing .prj) and names `--spacing`.
#[test]
fn a_geotiff_without_a_crs_is_said_in_geotiff_terms() {
    let dir = TempDir::new("nocrs");
    let path = dir.path().join("no_crs.tif");
    write_geotiff(&path, (33, 33), &[870.0; 33 * 33], [25.0, 25.0], [500_000.0, 5_200_000.0], &[], None);
    let hf = load_default(&path);
    let notes = hf.georef.notes.join("\n");
    let line = notes.lines().find(|l| l.contains("ASSUMED to be the metre")).unwrap_or_else(|| panic!("{notes}"));
    assert!(line.contains("the GeoTIFF tags") && line.contains("--spacing"), "{line}");
    assert!(!line.contains("world file") && !line.contains(".prj"), "{line}");
    assert!(!hf.georef.absolute_heights, "no CRS: heights relative unless declared");
    assert!(notes.contains("--heights absolute"), "{notes}");
}
