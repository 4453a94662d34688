//! The tile archive (issue 27, SPEC section 8): `prepare` writes, window by window, a
//! PMTiles quadtree whose tiles hold exactly the heights they should and the exact
//! camera-independent bound `D`; opening it gives back the terrain; every damaged byte,
//! a truncated file and an interrupted run are caught.

mod common;

use common::{cli, TempDir};
use std::path::Path;
use std::process::Command;
use std::sync::atomic::AtomicBool;
use vkterrain::input::archive::{Archive, TILE_QUADS};
use vkterrain::lod::heightfield::{HeightFormat, Heightfield};
use vkterrain::prepare::source::{InMemory, Synthetic};
use vkterrain::prepare::{prepare, Frame, PrepareError, Source};

fn frame_of(hf: &Heightfield) -> Frame {
    Frame {
        spacing: [hf.spacing.x, hf.spacing.z],
        height_scale: hf.height_scale,
        georef: hf.georef.clone(),
        void_samples: hf.void_samples,
    }
}

fn prepare_field(hf: &Heightfield, out: &Path) {
    let stop = AtomicBool::new(false);
    prepare(&InMemory(hf), &frame_of(hf), out, &|_, _| {}, &stop).expect("prepare");
}

/// A rough float field: value noise, a ridge, a pit and one spike, so that every level's
/// deviation is different and large somewhere.
fn rough(w: usize, h: usize) -> Heightfield {
    common::field(w, h, [3.0, 5.0], |x, z| {
        let n = ((x * 7919 + z * 104_729) % 1013) as f32 * 0.05;
        let ridge = 40.0 - ((x as f32 - 0.6 * z as f32).abs() * 0.3).min(40.0);
        let spike = if (x, z) == (w * 5 / 7, h / 3) { 900.0 } else { 0.0 };
        n + ridge + spike + ((x as f32 * 0.013).sin() * (z as f32 * 0.021).cos()) * 60.0
    })
}

/// The clamped sample (as `Heightfield::embed` extends the edges).
fn sample(hf: &Heightfield, x: i64, z: i64) -> f32 {
    let gw = hf.grid()[0];
    let (x, z) = (x.clamp(0, hf.width as i64 - 1) as usize, z.clamp(0, hf.height as i64 - 1) as usize);
    hf.raw[z * gw + x]
}

/// Independent oracle for `D` of group `(gx, gz)` of level `l` over the archive's
/// square: f64 barycentric interpolation over the quad's two triangles, samples limited
/// to the stored tiles (`cover` samples a side), 0 for groups starting past the extent.
fn oracle(hf: &Heightfield, cover: [i64; 2], l: u32, gx: i64, gz: i64) -> f64 {
    let s = 1i64 << l;
    let (cx, cz) = (gx * s, gz * s);
    if cx >= hf.width as i64 - 1 || cz >= hf.height as i64 - 1 {
        return 0.0;
    }
    let h = |x, z| sample(hf, x, z) as f64;
    let (a, c, g, i) = (h(cx, cz), h(cx + s, cz), h(cx, cz + s), h(cx + s, cz + s));
    let mut m = 0.0f64;
    for z in cz..=(cz + s).min(cover[1]) {
        for x in cx..=(cx + s).min(cover[0]) {
            let (u, v) = ((x - cx) as f64 / s as f64, (z - cz) as f64 / s as f64);
            // Triangle a-c-i where u >= v, else a-i-g.
            let l = if u >= v { a + (c - a) * u + (i - c) * v } else { a + (g - a) * v + (i - g) * u };
            m = m.max((h(x, z) - l).abs());
        }
    }
    m
}

/// Every stored tile against the field: heights (border included) and every `D` it
/// holds. Returns the mismatches, described.
fn check_archive(
    hf: &Heightfield,
    archive: &Archive,
    tamper: impl Fn(&mut vkterrain::input::archive::tile::Tile),
) -> Vec<String> {
    let m = &archive.meta;
    let t = TILE_QUADS as i64;
    let cover = m.tiles_at(0).map(|c| c as i64 * t);
    let mut bad = Vec::new();
    let mut deviations = 0usize;
    for level in 0..=m.top_level {
        let [nx, nz] = m.tiles_at(level);
        for tz in 0..nz {
            for tx in 0..nx {
                let mut tile = archive.read_tile(level, tx, tz).unwrap().expect("stored tile");
                tamper(&mut tile);
                let step = 1i64 << level;
                let (x0, z0) = (tx as i64 * t * step, tz as i64 * t * step);
                for j in -1..=t + 1 {
                    for i in -1..=t + 1 {
                        let got = tile.heights[((j + 1) * (t + 3) + i + 1) as usize];
                        let want = sample(hf, x0 + i * step, z0 + j * step);
                        if got != want {
                            bad.push(format!("level {level} tile ({tx},{tz}) vertex ({i},{j}): {got} vs {want}"));
                        }
                    }
                }
                // D of its own level, then (the top tile) every coarser level.
                let mut at = 0;
                let first = u32::from(level).max(1);
                let last = if level == m.top_level { m.n() } else { first };
                for l in first..=last {
                    if level == 0 && level != m.top_level {
                        break;
                    }
                    let side = ((TILE_QUADS << level) >> l).max(1) as i64;
                    for b in 0..side {
                        for a in 0..side {
                            let (gx, gz) = (tx as i64 * side + a, tz as i64 * side + b);
                            let want = oracle(hf, cover, l, gx, gz);
                            let got = tile.deviation[at] as f64;
                            at += 1;
                            if (got - want).abs() > 1e-4 * want.max(1.0) {
                                bad.push(format!(
                                    "D level {l} group ({gx},{gz}) from tile {level}/{tx}/{tz}: {got} vs {want}"
                                ));
                            }
                        }
                    }
                }
                assert_eq!(
                    at,
                    tile.deviation.len(),
                    "tile {level}/{tx}/{tz} holds {} values of D",
                    tile.deviation.len()
                );
                deviations += at;
            }
        }
    }
    assert!(deviations > 0);
    bad
}

#[test]
fn tiles_hold_the_exact_heights_and_bound_and_a_wrong_value_is_caught() {
    // 1100 x 700: 5 x 3 leaves, top level 3, groups of LOD 9-11 larger than a leaf
    // (their D from the leaves' shares and the lattice of corners); 513 x 513 in 16 bits
    // (top level 1); a 3 x 3 terrain (one tile holding every level).
    let fields = [
        rough(1100, 700),
        common::field16(513, 513, 10.0, 0.1, |x, z| (((x * 31 + z * 17) % 65536) ^ ((x * z) % 4096)) as u16),
        common::field(3, 3, 1.0, |x, z| (x * 3 + z) as f32 * if x == 1 && z == 1 { 9.0 } else { 1.0 }),
        // The highest and lowest samples alone, on the last column and the last row.
        common::field(600, 300, 1.0, |x, z| match (x, z) {
            (599, 7) => 900.0,
            (3, 299) => -40.0,
            _ => ((x * 7 + z) % 13) as f32,
        }),
    ];
    for hf in &fields {
        let dir = TempDir::new("archive-exact");
        let out = dir.path().join("t.pmtiles");
        prepare_field(hf, &out);
        let archive = Archive::open(&out).unwrap();
        assert_eq!((archive.meta.width, archive.meta.height), (hf.width, hf.height));
        // The range of every sample (a streamed terrain's colours and default view).
        let extent = (0..hf.height as i64).flat_map(|z| (0..hf.width as i64).map(move |x| (x, z)));
        let range = extent
            .map(|(x, z)| sample(hf, x, z))
            .fold([f32::INFINITY, f32::NEG_INFINITY], |[a, b], h| [a.min(h), b.max(h)]);
        assert_eq!(archive.meta.raw_range, Some(range), "{} x {}", hf.width, hf.height);
        let bad = check_archive(hf, &archive, |_| {});
        assert!(
            bad.is_empty(),
            "{} x {}: {} mismatches, first: {:?}",
            hf.width,
            hf.height,
            bad.len(),
            &bad[..bad.len().min(5)]
        );
        // The check can fail: one D lowered by a thousandth, one height changed.
        let tampered = check_archive(hf, &archive, |tile| {
            if let Some(d) = tile.deviation.iter_mut().find(|d| **d > 1.0) {
                *d *= 0.999;
            }
        });
        assert!(!tampered.is_empty(), "a lowered D went unnoticed");
        let tampered = check_archive(hf, &archive, |tile| tile.heights[tile.side + 5] += 1.0);
        assert!(!tampered.is_empty(), "a changed height went unnoticed");
    }
}

#[test]
fn an_archive_opens_as_the_terrain_it_was_made_from() {
    for hf in [rough(1100, 700), common::field16(600, 257, [2.0, 3.0], 0.25, |x, z| (x * 100 + z) as u16)] {
        let dir = TempDir::new("archive-open");
        let out = dir.path().join("t.pmtiles");
        prepare_field(&hf, &out);
        let back = Archive::open(&out).unwrap().heightfield().unwrap();
        assert_eq!((back.width, back.height, back.n, back.roots), (hf.width, hf.height, hf.n, hf.roots));
        assert!(back.raw == hf.raw, "samples differ");
        assert_eq!((back.spacing, back.height_scale, back.format), (hf.spacing, hf.height_scale, hf.format));
    }
}

#[test]
fn a_real_geotiff_keeps_its_georeferencing_through_the_archive() {
    let path = common::data("srtm3/mt_fuji_90m.tif");
    let hf = vkterrain::input::load::load(&path, &Default::default()).unwrap();
    let dir = TempDir::new("archive-geo");
    let out = dir.path().join("fuji.pmtiles");
    prepare_field(&hf, &out);
    let back = vkterrain::input::load::load(&out, &Default::default()).unwrap();
    assert!(back.raw == hf.raw);
    assert_eq!((back.spacing, back.height_scale, back.void_samples), (hf.spacing, hf.height_scale, hf.void_samples));
    assert!(hf.void_samples > 0, "the Fuji tile has voids (the archive keeps their count)");
    let (mut g, a) = (back.georef.clone(), &hf.georef);
    assert!(g.notes[0].contains("prepared archive"), "{:?}", g.notes);
    g.notes.remove(0);
    assert_eq!(&g, a);
}

#[test]
fn the_synthetic_source_is_a_source_like_any_other() {
    // Made window by window, or first as a heightfield: the same archive tiles.
    let side = 700;
    let synthetic = Synthetic { side };
    let samples: Vec<f32> = (0..side * side).map(|i| synthetic.raw(i % side, i / side)).collect();
    let hf = Heightfield::embed(
        "s",
        side,
        side,
        &samples,
        HeightFormat::Unorm16,
        Synthetic::SPACING,
        Synthetic::HEIGHT_SCALE,
    )
    .unwrap();
    let dir = TempDir::new("archive-synthetic");
    let (a, b) = (dir.path().join("a.pmtiles"), dir.path().join("b.pmtiles"));
    let stop = AtomicBool::new(false);
    let report = prepare(&synthetic, &frame_of(&hf), &a, &|_, _| {}, &stop).unwrap();
    prepare_field(&hf, &b);
    let (a, b) = (Archive::open(&a).unwrap(), Archive::open(&b).unwrap());
    assert_eq!(report.tiles, 9 + 4 + 1);
    assert_eq!(report.distinct_tiles, report.tiles, "non-periodic: every tile differs");
    for (level, tx, tz) in a.meta.tiles() {
        assert_eq!(a.read_tile(level, tx, tz).unwrap(), b.read_tile(level, tx, tz).unwrap());
    }
}

/// A source that fails after a number of reads (a disk error halfway).
struct Failing<'a>(InMemory<'a>, std::sync::atomic::AtomicUsize);

impl Source for Failing<'_> {
    fn name(&self) -> String {
        "failing".into()
    }
    fn size(&self) -> (usize, usize) {
        self.0.size()
    }
    fn samples(&self) -> vkterrain::input::archive::tile::Samples {
        self.0.samples()
    }
    fn read(&self, x0: i64, z0: i64, nx: usize, nz: usize, stride: usize, out: &mut Vec<f32>) -> Result<(), String> {
        if self.1.fetch_add(1, std::sync::atomic::Ordering::SeqCst) == 6 {
            return Err("failing: read error at window 6".into());
        }
        self.0.read(x0, z0, nx, nz, stride, out)
    }
}

#[test]
fn a_failed_or_interrupted_run_leaves_no_file() {
    let hf = rough(1100, 700);
    let dir = TempDir::new("archive-interrupt");
    let out = dir.path().join("t.pmtiles");
    let stop = AtomicBool::new(true);
    let e = prepare(&InMemory(&hf), &frame_of(&hf), &out, &|_, _| {}, &stop).unwrap_err();
    assert!(matches!(e, PrepareError::Interrupted), "{e}");
    let failing = Failing(InMemory(&hf), Default::default());
    let e = prepare(&failing, &frame_of(&hf), &out, &|_, _| {}, &AtomicBool::new(false)).unwrap_err();
    assert!(e.to_string().contains("read error at window 6"), "{e}");
    let left: Vec<_> = std::fs::read_dir(dir.path()).unwrap().collect();
    assert!(left.is_empty(), "left behind: {left:?}");
}

#[test]
fn prepare_then_render_end_to_end_with_validation_and_identical_frames() {
    let dir = TempDir::new("archive-cli");
    let out = dir.path().join("rainier.pmtiles");
    let input = common::data("srtm3/mt_rainier_90m.tif");
    let o = cli(&["prepare", input.to_str().unwrap(), "--out", out.to_str().unwrap()]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let report: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    assert_eq!(report["report"]["tiles"], 25 + 9 + 4 + 1);
    let render = |heightmap: &Path, png: &str| {
        let png = dir.path().join(png);
        let o = cli(&[
            "render",
            "--heightmap",
            heightmap.to_str().unwrap(),
            "--validation",
            "on",
            "--size",
            "320x240",
            "--out",
            png.to_str().unwrap(),
        ]);
        assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
        let json: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
        assert_eq!(json["validation_messages"], 0);
        (std::fs::read(png).unwrap(), String::from_utf8_lossy(&o.stderr).into_owned())
    };
    let (direct, _) = render(&input, "direct.png");
    let (archived, notes) = render(&out, "archived.png");
    assert!(notes.contains("EPSG:4326") && notes.contains("prepared archive"), "{notes}");
    assert!(direct == archived, "the archive renders a different frame");
}

#[test]
fn a_damaged_archive_is_refused_naming_the_file_and_the_tile() {
    let dir = TempDir::new("archive-damage");
    let good = dir.path().join("good.pmtiles");
    let o = cli(&["prepare", "--synthetic", "600", "--out", good.to_str().unwrap()]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let bytes = std::fs::read(&good).unwrap();
    let open = |name: &str, data: &[u8]| {
        let p = dir.path().join(name);
        std::fs::write(&p, data).unwrap();
        let o = cli(&[
            "render",
            "--heightmap",
            p.to_str().unwrap(),
            "--size",
            "64x64",
            "--out",
            dir.path().join("x.png").to_str().unwrap(),
        ]);
        assert_eq!(o.status.code(), Some(2), "{name}: {}", String::from_utf8_lossy(&o.stderr));
        let e = String::from_utf8_lossy(&o.stderr).into_owned();
        assert!(e.contains(p.to_str().unwrap()), "{name}: the message names the file: {e}");
        e
    };
    let o = cli(&["check", good.to_str().unwrap()]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let checked: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    assert_eq!(checked["tiles_checked"], 14);
    // A byte in the middle of the tile data, bytes in a few other tiles: `render` and
    // `check` both refuse them.
    for at in [16_384 + 10, bytes.len() / 2, bytes.len() - 100] {
        let mut bad = bytes.clone();
        bad[at] ^= 0x5a;
        let e = open("flipped.pmtiles", &bad);
        assert!(e.contains("tile ") && (e.contains("corrupt") || e.contains("checksum")), "byte {at}: {e}");
        let o = cli(&["check", dir.path().join("flipped.pmtiles").to_str().unwrap()]);
        assert_eq!(o.status.code(), Some(2), "check accepted byte {at} flipped");
    }
    // Header fields the metadata contradicts: a tile count, the zooms.
    for (at, what) in [(72, "addressed tiles"), (80, "addressed tiles"), (101, "zooms")] {
        let mut bad = bytes.clone();
        bad[at] ^= 0x01;
        let e = open("header-field.pmtiles", &bad);
        assert!(e.contains(what), "byte {at}: {e}");
    }
    // Header words that contradict the file (an adversarial review found `check` calling
    // each of these intact): the tile data's length (0, 1, past the end, overflowing), the
    // leaf directories' offset and length (there are none), the root directory's and the
    // metadata's lengths (overlapping what follows).
    let word = |at: usize, v: u64| {
        let mut b = bytes.clone();
        b[at..at + 8].copy_from_slice(&v.to_le_bytes());
        b
    };
    for (at, v) in
        [(64, 0), (64, 1), (64, 9_999_999_999), (64, u64::MAX), (40, u64::MAX), (48, 5), (16, 100_000), (32, 100_000)]
    {
        let p = dir.path().join("contradicts.pmtiles");
        std::fs::write(&p, word(at, v)).unwrap();
        let o = cli(&["check", p.to_str().unwrap()]);
        let e = String::from_utf8_lossy(&o.stderr);
        assert_eq!(o.status.code(), Some(2), "check accepted header word at {at} = {v}: {e}");
        assert!(e.contains("contradicts.pmtiles") && (e.contains("header") || e.contains("tile ")), "{e}");
    }
    let e = open("truncated.pmtiles", &bytes[..bytes.len() * 2 / 3]);
    assert!(e.contains("tile ") && e.contains("truncated"), "{e}");
    let e = open("header.pmtiles", &bytes[..60]);
    assert!(e.contains("shorter than a PMTiles header") || e.contains("past the end"), "{e}");
    let e = open("garbage.pmtiles", b"this is not an archive at all, just text of some length........................................................................................");
    assert!(e.contains("not a PMTiles archive"), "{e}");
    assert!(!dir.path().join("x.png").exists());
}

/// Every tile of two archives, and their metadata, equal.
fn same_archives(a: &Path, b: &Path) {
    let (a, b) = (Archive::open(a).unwrap(), Archive::open(b).unwrap());
    assert_eq!(a.meta, b.meta);
    for level in 0..=a.meta.top_level {
        let [nx, nz] = a.meta.tiles_at(level);
        for (tx, tz) in (0..nz).flat_map(|z| (0..nx).map(move |x| (x, z))) {
            assert_eq!(
                a.read_tile(level, tx, tz).unwrap(),
                b.read_tile(level, tx, tz).unwrap(),
                "tile {level}/{tx}/{tz}"
            );
        }
    }
}

#[test]
fn reading_window_by_window_makes_the_same_archive_as_reading_whole() {
    let dir = TempDir::new("archive-windows");
    let canyon = common::data("grand_canyon/gcanyon_height_4k2k.png");
    // A south-up, west-running float GeoTIFF in UTM (mirrored on reading, both ways).
    let mirrored = dir.path().join("mirrored.tif");
    {
        let driver = gdal::DriverManager::get_driver_by_name("GTiff").unwrap();
        let (w, h) = (700usize, 530usize);
        let mut ds = driver.create_with_band_type::<f32, _>(&mirrored, w, h, 1).unwrap();
        ds.set_geo_transform(&[500_000.0, -25.0, 0.0, 5_200_000.0, 0.0, 25.0]).unwrap();
        ds.set_spatial_ref(&gdal::spatial_ref::SpatialRef::from_epsg(32610).unwrap()).unwrap();
        let samples: Vec<f32> =
            (0..w * h).map(|i| ((i % w) as f32 * 0.05).sin() * 300.0 + (i / w) as f32 * 0.7).collect();
        let mut buf = gdal::raster::Buffer::new((w, h), samples);
        ds.rasterband(1).unwrap().write((0, 0), (w, h), &mut buf).unwrap();
    }
    // The canyon carries no georeferencing: both reads must recognise it as the known
    // data set (60 m, 10 m a unit), not fall back to a default.
    for (input, extra) in [(&canyon, &[][..]), (&mirrored, &[][..])] {
        let (whole, windows) = (dir.path().join("whole.pmtiles"), dir.path().join("windows.pmtiles"));
        for (out, flag) in [(&whole, None), (&windows, Some("--windows"))] {
            let mut args = vec!["prepare", input.to_str().unwrap(), "--out", out.to_str().unwrap()];
            args.extend_from_slice(extra);
            args.extend(flag);
            let o = cli(&args);
            assert!(o.status.success(), "{:?}: {}", args, String::from_utf8_lossy(&o.stderr));
            let notes = String::from_utf8_lossy(&o.stderr);
            assert_eq!(notes.contains("read window by window"), flag.is_some(), "{notes}");
        }
        same_archives(&whole, &windows);
        // Tiles are stored in tile-id order whatever order the workers made them in.
        assert!(std::fs::read(&whole).unwrap() == std::fs::read(&windows).unwrap(), "{input:?}: not the same bytes");
        if input == &canyon {
            let m = Archive::open(&windows).unwrap().meta;
            assert_eq!((m.spacing, m.height_scale), ([60.0, 60.0], 10.0), "the canyon's documented scale");
        }
    }
}

/// Runs `vkterrain ARGS` and expects exit 2 within a minute with one error line holding
/// every needle (a FIFO input must not block the run).
fn refused(args: &[&str], needles: &[&str]) {
    let o = common::run_bounded(&args.iter().map(|a| a.to_string()).collect::<Vec<_>>(), 60);
    let e = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(2), "{args:?}: {e}");
    // Notes and the progress line of a run that started are not errors.
    let lines: Vec<&str> =
        e.lines().filter(|l| !l.starts_with("vkterrain: note:") && !l.starts_with("vkterrain: preparing ")).collect();
    assert_eq!(lines.len(), 1, "{args:?}: one error line: {e}");
    for n in needles {
        assert!(lines[0].contains(n), "{args:?}: '{}' does not mention '{n}'", lines[0]);
    }
}

/// What an adversarial review of `prepare` and `check` found: an `--out` that is the
/// input (under any spelling) overwrote it; a FIFO hung both commands; a missing argument
/// was not named; a missing output directory exited 1 with its cause printed twice;
/// scales no renderer accepts made archives it refused.
#[test]
fn prepare_and_check_refuse_what_would_destroy_hang_or_mislead() {
    let dir = TempDir::new("archive-refuse");
    let d = dir.path();
    let input = d.join("rainier.tif");
    std::fs::copy(common::data("srtm3/mt_rainier_90m.tif"), &input).unwrap();
    let original = std::fs::read(&input).unwrap();
    std::fs::create_dir(d.join("o")).unwrap();
    std::fs::hard_link(&input, d.join("o/linked.tif")).unwrap();
    let i = input.to_str().unwrap();
    let respelled = d.join("o/../rainier.tif");
    let linked = d.join("o/linked.tif");
    for out in [&input, &respelled, &linked] {
        refused(&["prepare", i, "--out", out.to_str().unwrap()], &["--out", "is the input"]);
    }
    assert!(std::fs::read(&input).unwrap() == original, "the input was changed");
    let archive = d.join("a.pmtiles");
    let o = cli(&["prepare", "--synthetic", "65", "--out", archive.to_str().unwrap()]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let a = archive.to_str().unwrap();
    refused(&["prepare", a, "--out", a], &["--out", "is the input"]);
    assert!(Archive::open(&archive).is_ok(), "the archive survives");

    let fifo = d.join("fifo.tif");
    assert!(Command::new("mkfifo").arg(&fifo).status().unwrap().success());
    let f = fifo.to_str().unwrap();
    let out = d.join("x.pmtiles");
    let x = out.to_str().unwrap();
    refused(&["prepare", f, "--out", x], &[f, "not a regular file"]);
    refused(&["prepare", f, "--windows", "--out", x], &[f, "not a regular file"]);
    refused(&["check", f], &[f, "not a regular file"]);

    refused(&["prepare", "--out", x], &["required", "<INPUT>"]);
    refused(&["check"], &["required", "<ARCHIVE>"]);

    let missing = d.join("no/such/dir/x.pmtiles");
    refused(&["prepare", "--synthetic", "65", "--out", missing.to_str().unwrap()], &["no/such/dir/x.pmtiles"]);
    let o = cli(&["prepare", "--synthetic", "65", "--out", missing.to_str().unwrap()]);
    let e = String::from_utf8_lossy(&o.stderr);
    assert!(e.matches("os error").count() <= 1 && !e.contains("preparing"), "before the run, the cause once: {e}");

    // A name that says another format is refused (the archive would pass for a PNG).
    let png = d.join("x.png");
    refused(&["prepare", "--synthetic", "65", "--out", png.to_str().unwrap()], &["x.png", ".pmtiles"]);
    for (flag, value) in [("--height-scale", "1e30"), ("--spacing", "1e30")] {
        refused(&["prepare", "--synthetic", "65", flag, value, "--out", x], &["beyond 1e12"]);
    }
    let left: Vec<_> = std::fs::read_dir(d).unwrap().flatten().map(|e| e.file_name()).collect();
    assert_eq!(left.len(), 4, "nothing new beside the inputs: {left:?}");
}

/// Each tenth of the windows is reported once when stderr is not a terminal, the last
/// one included, however many windows there are (it printed every window at 16 and
/// nothing at 9 or fewer).
#[test]
fn progress_off_a_terminal_is_ten_lines_ending_at_the_total() {
    let dir = TempDir::new("archive-progress");
    for (side, windows) in [(65u32, 1u64), (769, 9), (1025, 16)] {
        let out = dir.path().join(format!("p{side}.pmtiles"));
        let o = cli(&["prepare", "--synthetic", &side.to_string(), "--out", out.to_str().unwrap()]);
        assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
        let e = String::from_utf8_lossy(&o.stderr);
        let lines: Vec<&str> = e.lines().filter(|l| l.contains("windows,")).collect();
        assert_eq!(lines.len() as u64, windows.min(10), "{side}: {e}");
        assert!(lines.last().unwrap().contains(&format!("{windows} of {windows} windows")), "{side}: {e}");
    }
}

/// A run stopped by SIGINT, SIGTERM or SIGHUP cleans up (no file) and exits 128 + the
/// signal (130, 143, 129), as a shell expects; a partial file left by a run that could
/// not clean up (SIGKILL) is removed by the next run.
#[test]
fn a_terminated_run_leaves_nothing_and_stale_partials_are_removed() {
    for (signal, code) in [("TERM", 143), ("HUP", 129), ("INT", 130)] {
        let dir = TempDir::new("archive-term");
        let out = dir.path().join("t.pmtiles");
        let stale = dir.path().join(".t.pmtiles.partial-999999999");
        std::fs::write(&stale, b"left by a killed run").unwrap();
        let mut child = Command::new(env!("CARGO_BIN_EXE_vkterrain"))
            .args(["prepare", "--synthetic", "4097", "--out", out.to_str().unwrap()])
            .env("RUST_LOG", "error")
            .stdout(std::process::Stdio::null())
            .stderr(std::process::Stdio::null())
            .spawn()
            .unwrap();
        let own = dir.path().join(format!(".t.pmtiles.partial-{}", child.id()));
        // Wait (by polling the condition, not a fixed sleep) for the run's own partial file.
        let started = std::time::Instant::now();
        while !own.exists() {
            assert!(child.try_wait().unwrap().is_none(), "SIG{signal}: the run ended before it was stopped");
            assert!(started.elapsed().as_secs() < 120, "SIG{signal}: no partial file after 120 s");
            std::thread::sleep(std::time::Duration::from_millis(5));
        }
        assert!(!stale.exists(), "the stale partial of a dead process is removed");
        let kill = Command::new("kill").args([&format!("-{signal}"), &child.id().to_string()]).status().unwrap();
        assert!(kill.success());
        let status = child.wait().unwrap();
        assert_eq!(status.code(), Some(code), "SIG{signal}: {status:?}");
        let left: Vec<_> = std::fs::read_dir(dir.path()).unwrap().flatten().map(|e| e.file_name()).collect();
        assert!(left.is_empty(), "SIG{signal}: left behind: {left:?}");
    }
}

/// A void read window by window is refused naming the sample, why it is not filled
/// (that read, not the input's size: this one fits in memory) and what to do; read whole,
/// the same file prepares with its voids filled.
#[test]
fn voids_read_window_by_window_are_refused_naming_the_sample() {
    let dir = TempDir::new("archive-voids");
    let out = dir.path().join("fuji.pmtiles");
    let fuji = common::data("srtm3/mt_fuji_90m.tif");
    refused(
        &["prepare", fuji.to_str().unwrap(), "--windows", "--out", out.to_str().unwrap()],
        &["mt_fuji_90m.tif", "column", "void", "read window by window", "gdal_fillnodata"],
    );
    let left: Vec<_> = std::fs::read_dir(dir.path()).unwrap().collect();
    assert!(left.is_empty(), "left behind: {left:?}");
    let o = cli(&["prepare", fuji.to_str().unwrap(), "--out", out.to_str().unwrap()]);
    assert!(o.status.success(), "read whole, voids are filled: {}", String::from_utf8_lossy(&o.stderr));
}

/// An archive as the input of `prepare` is read tile by tile, not whole: the same tiles
/// come out, and the peak memory stays below what the whole terrain takes in memory
/// (4097^2 samples as f32, twice: 134 MB).
#[test]
fn an_archive_reprepared_tile_by_tile_gives_the_same_tiles_in_bounded_memory() {
    let dir = TempDir::new("archive-reprepare");
    let (first, second) = (dir.path().join("a.pmtiles"), dir.path().join("b.pmtiles"));
    let o = cli(&["prepare", "--synthetic", "4097", "--out", first.to_str().unwrap()]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let o = cli(&["prepare", first.to_str().unwrap(), "--out", second.to_str().unwrap()]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    assert!(String::from_utf8_lossy(&o.stderr).contains("read tile by tile"));
    let report: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    let peak = report["peak_resident_mb"].as_f64().unwrap();
    assert!(peak < 120.0, "re-preparing 4097^2 peaked at {peak:.0} MB: read whole?");
    let (a, b) = (Archive::open(&first).unwrap(), Archive::open(&second).unwrap());
    assert_eq!(a.meta, vkterrain::input::archive::Meta { source: a.meta.source.clone(), ..b.meta.clone() });
    for (level, tx, tz) in a.meta.tiles() {
        assert_eq!(a.read_tile(level, tx, tz).unwrap(), b.read_tile(level, tx, tz).unwrap(), "tile {level}/{tx}/{tz}");
    }
}

/// Two runs over the same input write the same bytes (the workers finish tiles in a
/// different order every run; the data section is put in tile-id order, PMTiles'
/// "clustered"), and nothing is left beside the archive.
#[test]
fn the_same_input_makes_the_same_bytes() {
    let dir = TempDir::new("archive-reproducible");
    let runs: Vec<Vec<u8>> = (0..3)
        .map(|i| {
            let out = dir.path().join(format!("r{i}.pmtiles"));
            let o = cli(&["prepare", "--synthetic", "1537", "--out", out.to_str().unwrap()]);
            assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
            std::fs::read(&out).unwrap()
        })
        .collect();
    assert!(runs[0] == runs[1] && runs[1] == runs[2], "runs differ");
    let header = vkterrain::input::archive::pmtiles::Header::decode(&runs[0]).unwrap();
    assert!(header.clustered);
    let left: Vec<_> = std::fs::read_dir(dir.path()).unwrap().flatten().map(|e| e.file_name()).collect();
    assert_eq!(left.len(), 3, "{left:?}");
}

/// Many tiles in, one terrain out: the Rainier SRTM tile cut into four GeoTIFFs (each
/// with its own geotransform, two of them in a subdirectory), given as files or as their
/// directory, prepares into the
/// same tiles as the whole; a tile in another CRS is refused naming it, not skipped.
#[test]
fn a_mosaic_of_tiles_prepares_like_the_whole() {
    let dir = TempDir::new("archive-mosaic");
    let whole = common::data("srtm3/mt_rainier_90m.tif");
    let ds = gdal::Dataset::open(&whole).unwrap();
    let (w, h) = ds.raster_size();
    let t = ds.geo_transform().unwrap();
    let srs = ds.spatial_ref().unwrap();
    let band = ds.rasterband(1).unwrap();
    let pieces = dir.path().join("pieces");
    std::fs::create_dir_all(pieces.join("south")).unwrap();
    let driver = gdal::DriverManager::get_driver_by_name("GTiff").unwrap();
    let (cx, cz) = (w / 2 + 7, h / 3);
    let mut names = Vec::new();
    for (i, (x0, z0, x1, z1)) in
        [(0, 0, cx, cz), (cx, 0, w, cz), (0, cz, cx, h), (cx, cz, w, h)].into_iter().enumerate()
    {
        let name =
            if i < 2 { pieces.join(format!("piece{i}.tif")) } else { pieces.join(format!("south/piece{i}.tif")) };
        let buf =
            band.read_as::<f32>((x0 as isize, z0 as isize), (x1 - x0, z1 - z0), (x1 - x0, z1 - z0), None).unwrap();
        let mut out = driver.create_with_band_type::<f32, _>(&name, x1 - x0, z1 - z0, 1).unwrap();
        out.set_geo_transform(&[t[0] + x0 as f64 * t[1], t[1], 0.0, t[3] + z0 as f64 * t[5], 0.0, t[5]]).unwrap();
        out.set_spatial_ref(&srs).unwrap();
        let mut buf = buf;
        let mut piece = out.rasterband(1).unwrap();
        piece.set_no_data_value(band.no_data_value()).unwrap();
        piece.write((0, 0), (x1 - x0, z1 - z0), &mut buf).unwrap();
        names.push(name.to_str().unwrap().to_string());
    }
    let reference = dir.path().join("whole.pmtiles");
    let o = cli(&["prepare", whole.to_str().unwrap(), "--out", reference.to_str().unwrap()]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let from_files = dir.path().join("files.pmtiles");
    let mut args = vec!["prepare"];
    args.extend(names.iter().map(String::as_str));
    args.extend(["--out", from_files.to_str().unwrap()]);
    let o = cli(&args);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    assert!(String::from_utf8_lossy(&o.stderr).contains("a mosaic of 4 files"));
    let from_dir = dir.path().join("dir.pmtiles");
    let o = cli(&["prepare", pieces.to_str().unwrap(), "--out", from_dir.to_str().unwrap()]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    // Named by its files, not by its temporary VRT: the same bytes however it was given.
    assert!(std::fs::read(&from_files).unwrap() == std::fs::read(&from_dir).unwrap(), "mosaics differ");
    let a = Archive::open(&reference).unwrap();
    for other in [&from_files, &from_dir] {
        let b = Archive::open(other).unwrap();
        assert_eq!(a.meta, vkterrain::input::archive::Meta { source: a.meta.source.clone(), ..b.meta.clone() });
        for (level, tx, tz) in a.meta.tiles() {
            assert_eq!(
                a.read_tile(level, tx, tz).unwrap(),
                b.read_tile(level, tx, tz).unwrap(),
                "{other:?}: tile {level}/{tx}/{tz}"
            );
        }
    }
    // A tile in another CRS.
    let utm = pieces.join("piece9.tif");
    {
        let mut out = driver.create_with_band_type::<f32, _>(&utm, 10, 10, 1).unwrap();
        out.set_geo_transform(&[500_000.0, 90.0, 0.0, 5_200_000.0, 0.0, -90.0]).unwrap();
        out.set_spatial_ref(&gdal::spatial_ref::SpatialRef::from_epsg(32610).unwrap()).unwrap();
    }
    let bad = dir.path().join("bad.pmtiles");
    refused(&["prepare", pieces.to_str().unwrap(), "--out", bad.to_str().unwrap()], &["piece9.tif", "CRS"]);
    std::fs::remove_file(&utm).unwrap();
    // A tile at another resolution (GDAL would resample all of them to the average).
    let coarse = pieces.join("piece8.tif");
    {
        let mut out = driver.create_with_band_type::<f32, _>(&coarse, 10, 10, 1).unwrap();
        out.set_geo_transform(&[t[0], 2.0 * t[1], 0.0, t[3], 0.0, 2.0 * t[5]]).unwrap();
        out.set_spatial_ref(&srs).unwrap();
    }
    refused(&["prepare", pieces.to_str().unwrap(), "--out", bad.to_str().unwrap()], &["piece8.tif", "resolution"]);
    // Off the grid by a third of a sample (GDAL would shift it).
    std::fs::remove_file(&coarse).unwrap();
    let shifted = pieces.join("piece7.tif");
    {
        let mut out = driver.create_with_band_type::<f32, _>(&shifted, 10, 10, 1).unwrap();
        out.set_geo_transform(&[t[0] + t[1] / 3.0, t[1], 0.0, t[3], 0.0, t[5]]).unwrap();
        out.set_spatial_ref(&srs).unwrap();
    }
    refused(&["prepare", pieces.to_str().unwrap(), "--out", bad.to_str().unwrap()], &["piece7.tif", "grid"]);
    // Another data type: GDAL's mosaic would leave the tile out with only a warning.
    std::fs::remove_file(&shifted).unwrap();
    let int16 = pieces.join("piece6.tif");
    {
        let mut out = driver.create_with_band_type::<i16, _>(&int16, 10, 10, 1).unwrap();
        out.set_geo_transform(&[t[0] + 2000.0 * t[1], t[1], 0.0, t[3], 0.0, t[5]]).unwrap();
        out.set_spatial_ref(&srs).unwrap();
    }
    refused(&["prepare", pieces.to_str().unwrap(), "--out", bad.to_str().unwrap()], &["piece6.tif", "left it out"]);
    // Two tiles 40,000 samples apart: a strip longer than a whole read takes is read
    // window by window, and the gap between them (voids) is refused naming the mosaic by
    // its files, not by its temporary VRT.
    std::fs::remove_file(&int16).unwrap();
    let strip = dir.path().join("strip");
    std::fs::create_dir(&strip).unwrap();
    for (i, x0) in [0.0, 40_000.0].into_iter().enumerate() {
        let mut out = driver.create_with_band_type::<f32, _>(strip.join(format!("s{i}.tif")), 10, 10, 1).unwrap();
        out.set_geo_transform(&[t[0] + x0 * t[1], t[1], 0.0, t[3], 0.0, t[5]]).unwrap();
        out.set_spatial_ref(&srs).unwrap();
        let mut band = out.rasterband(1).unwrap();
        band.set_no_data_value(Some(-32768.0)).unwrap();
        band.write((0, 0), (10, 10), &mut gdal::raster::Buffer::new((10, 10), vec![100.0f32; 100])).unwrap();
    }
    let o = common::run_bounded(
        &["prepare".into(), strip.display().to_string(), "--out".into(), bad.display().to_string()],
        60,
    );
    let e = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(2), "{e}");
    assert!(e.contains("read window by window") && e.contains("a mosaic of 2 files"), "{e}");
    assert!(!e.contains("mosaic.vrt") && !e.contains("vkterrain prepare"), "{e}");
    let empty = dir.path().join("empty");
    std::fs::create_dir(&empty).unwrap();
    refused(&["prepare", empty.to_str().unwrap(), "--out", bad.to_str().unwrap()], &["no elevation tiles"]);
    let leftovers = std::fs::read_dir(std::env::temp_dir())
        .unwrap()
        .flatten()
        .filter(|e| e.file_name().to_string_lossy().starts_with("vkterrain-mosaic-"))
        .count();
    assert_eq!(leftovers, 0, "a mosaic directory was left in the temporary directory");
}

/// `--voids hole` from tiles: `prepare --voids hole` keeps which samples were voids, and
/// a frame drawn from that archive, or from the file cut into tiles, cuts the holes the
/// file drawn in memory cuts. With every block at LOD 0 (`--lod full`, each drawn from a
/// level-0 tile, whose mask is the file's) the same pixels show the background and the
/// exported mesh leaves out the same triangles. At the default LOD the blocks holding a
/// void are drawn at LOD 0 (a coarser tile's flags cover their vertices' neighbourhoods,
/// so they find them): the holes are memory's give or take the selections' outlines,
/// and the mesh leaves out at least the triangles `--lod full` does. Drawn filled, the archive shows no hole; an archive
/// prepared without the mask refuses `--voids hole`, saying so. Mount Fuji's SRTM tile
/// has 2,437 voids, most on the high ground.
#[test]
fn voids_drawn_as_holes_from_tiles_are_the_holes_drawn_in_memory() {
    let dir = TempDir::new("archive-holes");
    let fuji = common::data("srtm3/mt_fuji_90m.tif");
    let fuji = fuji.to_str().unwrap();
    let masked = dir.path().join("masked.pmtiles");
    let plain = dir.path().join("plain.pmtiles");
    for (out, extra) in [(&masked, &["--voids", "hole"][..]), (&plain, &[][..])] {
        let o = cli(&[&["prepare", fuji, "--out", out.to_str().unwrap()][..], extra].concat());
        assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    }
    // Straight down over the whole tile, the background magenta, no sun (plain colours).
    let render = |input: &[&str], lod: &str, voids: &str, name: &str| {
        let png = dir.path().join(format!("{name}.png"));
        let glb = dir.path().join(format!("{name}.glb"));
        let view = [
            "--lod",
            lod,
            "--voids",
            voids,
            "--camera",
            "60000,60000,60000",
            "--look-at",
            "60000,0,60001",
            "--size",
            "480x360",
            "--background",
            "1,0,1",
            "--sun",
            "off",
            "--validation",
            "on",
        ];
        let (png_s, glb_s) = (png.to_str().unwrap(), glb.to_str().unwrap());
        let args = [&["render"][..], input, &view, &["--out", png_s, "--export-mesh", glb_s]].concat();
        let o = cli(&args);
        assert!(o.status.success(), "{args:?}: {}", String::from_utf8_lossy(&o.stderr));
        let json = common::json_in(&String::from_utf8_lossy(&o.stdout));
        assert_eq!(json["validation_messages"], 0, "{args:?}");
        assert_eq!(json["voids"], voids, "{args:?}");
        let img = image::open(&png).unwrap().to_rgba8();
        let magenta: Vec<bool> = img.pixels().map(|p| p.0 == [255, 0, 255, 255]).collect();
        (magenta, json["mesh_triangles_in_holes"].as_u64().unwrap_or(0))
    };
    let masked = masked.to_str().unwrap();
    let (filled, _) = render(&[fuji], "full", "fill", "filled");
    // Holes: background where the filled terrain shows ground.
    let holes = |m: &[bool]| -> Vec<bool> { m.iter().zip(&filled).map(|(h, f)| *h && !*f).collect() };
    let count = |h: &[bool]| h.iter().filter(|v| **v).count();
    let differ = |a: &[bool], b: &[bool]| a.iter().zip(b).filter(|(a, b)| a != b).count();
    let (memory, memory_cut) = render(&[fuji], "full", "hole", "memory");
    let memory = holes(&memory);
    let n = count(&memory);
    assert!(n > 150 && memory_cut > 1000, "{n} hole pixels, {memory_cut} triangles in holes in memory");
    for (what, input) in [("the archive", &[masked][..]), ("the file cut into tiles", &[fuji, "--stream"][..])] {
        let (tiles, cut) = render(input, "full", "hole", "tiles");
        let tiles = holes(&tiles);
        let d = differ(&memory, &tiles);
        println!("{what}, LOD 0: {} hole pixels against {n} in memory, {d} differ", count(&tiles));
        assert!(d * 50 <= n, "{what}: {d} of {n} hole pixels differ from memory's");
        assert_eq!(cut, memory_cut, "{what}: triangles left out of the mesh");
    }
    let (memory_lod, memory_lod_cut) = render(&[fuji], "error", "hole", "memory-lod");
    let (tiles_lod, tiles_lod_cut) = render(&[masked], "error", "hole", "tiles-lod");
    let (memory_lod, tiles_lod) = (holes(&memory_lod), holes(&tiles_lod));
    let (a, b) = (count(&memory_lod), count(&tiles_lod));
    // A coarser block's holes lie where the file's are, give or take its tile's spacing.
    let near = |p: usize, within: i64| {
        let (x, y) = ((p % 480) as i64, (p / 480) as i64);
        (-within..=within).any(|dy| {
            (-within..=within).any(|dx| {
                let (u, v) = (x + dx, y + dy);
                (0..480).contains(&u) && (0..360).contains(&v) && memory_lod[(v * 480 + u) as usize]
            })
        })
    };
    let placed: Vec<usize> = (0..tiles_lod.len()).filter(|&p| tiles_lod[p]).collect();
    let far: Vec<usize> = (1..6).map(|w| placed.iter().filter(|&&p| !near(p, w)).count()).collect();
    println!(
        "default LOD: {b} hole pixels from tiles, {a} in memory, {} differ; from tiles, farther than 1..5 px from memory's: {far:?}; mesh triangles in holes {tiles_lod_cut} from tiles, {memory_lod_cut} in memory",
        differ(&memory_lod, &tiles_lod)
    );
    // (Pixels at the terrain's far edge, whose outline differs between selections,
    // count as holes here too: a few lie farther.)
    assert!(b * 10 >= a * 9 && b * 10 <= a * 11, "{b} hole pixels from tiles against {a} in memory");
    assert!(far[1] * 20 <= b, "{} of {b} hole pixels from tiles lie over 2 px from memory's", far[1]);
    // Blocks holding voids are drawn at LOD 0, whose tiles the mesh's holes come from.
    assert!(tiles_lod_cut >= memory_cut, "{tiles_lod_cut} mesh triangles in holes at the default LOD");
    let (shown, _) = render(&[masked], "full", "fill", "masked-filled");
    assert_eq!(count(&holes(&shown)), 0, "an archive drawn filled shows holes");
    let refused_png = dir.path().join("refused.png");
    let o = cli(&["render", plain.to_str().unwrap(), "--voids", "hole", "--out", refused_png.to_str().unwrap()]);
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(
        o.status.code() == Some(2) && err.contains("plain.pmtiles") && err.contains("2437 voids were filled"),
        "{err}"
    );
}
