//! Bad inputs get a clean error: exit code 2, one line naming the file or option and the
//! problem, no panic, and no output file left behind. The corpus is tests/bad_inputs/.

mod common;

use std::path::{Path, PathBuf};
use std::process::Command;

fn corpus(name: &str) -> String {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/bad_inputs").join(name).display().to_string()
}

/// A private scratch directory, removed with everything in it when dropped: tests leave
/// nothing behind in the temporary directory.
struct Scratch(PathBuf);

impl Scratch {
    fn new() -> Self {
        static NEXT: std::sync::atomic::AtomicUsize = std::sync::atomic::AtomicUsize::new(0);
        let n = NEXT.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
        let dir = std::env::temp_dir().join(format!("vkterrain-bad-{}-{n}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        Scratch(dir)
    }
    fn path(&self, name: &str) -> PathBuf {
        self.0.join(name)
    }
}

impl Drop for Scratch {
    fn drop(&mut self) {
        let _ = std::fs::remove_dir_all(&self.0);
    }
}

/// Runs `vkterrain ARGS` and checks the clean failure; `needles` must all appear in the
/// one error line.
fn fails_cleanly(args: &[&str], needles: &[&str]) {
    let scratch = Scratch::new();
    let out_png = scratch.path("out.png");
    let _ = std::fs::remove_file(&out_png);
    let mut full: Vec<String> = args.iter().map(|s| s.to_string()).collect();
    if args.first() == Some(&"render") && !args.contains(&"--out") {
        full.extend(["--out".into(), out_png.display().to_string()]);
    }
    let out = common::run_bounded(&full, 60);
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert_eq!(out.status.code(), Some(2), "{full:?}: exit {:?}, stderr: {stderr}", out.status.code());
    assert!(!stderr.contains("panicked"), "{full:?} panicked: {stderr}");
    let errors: Vec<&str> = stderr
        .lines()
        .filter(|l| l.starts_with("vkterrain:") && !l.contains("queue mode") && !l.starts_with("vkterrain: note:"))
        // Progress of a file prepared on the fly for streaming, not an error.
        .filter(|l| !l.starts_with("vkterrain: preparing ") && !l.starts_with("vkterrain: prepare: "))
        .collect();
    assert_eq!(errors.len(), 1, "{full:?}: expected one error line, got: {stderr}");
    for n in needles {
        assert!(errors[0].contains(n), "{full:?}: '{}' does not mention '{n}'", errors[0]);
    }
    assert!(!out_png.exists(), "{full:?} left {}", out_png.display());
    let dir = out_png.parent().unwrap();
    let partial: Vec<_> = std::fs::read_dir(dir)
        .unwrap()
        .flatten()
        .filter(|e| e.file_name().to_string_lossy().contains(".partial"))
        .map(|e| e.path())
        .collect();
    assert!(partial.is_empty(), "{full:?} left {partial:?}");
}

fn bad_file(name: &str, needles: &[&str]) {
    let path = corpus(name);
    let mut n = vec![name];
    n.extend_from_slice(needles);
    fails_cleanly(&["render", "--heightmap", &path, "--lod", "full", "--size", "64x48"], &n);
}

#[test]
fn truncated_png() {
    bad_file("truncated.png", &["cannot decode"]);
}
#[test]
fn corrupt_png() {
    bad_file("corrupt.png", &["cannot decode"]);
}
#[test]
fn colour_png() {
    bad_file("colour.png", &["colour image"]);
}
#[test]
fn zero_by_zero_png() {
    bad_file("zero_by_zero.png", &[]);
}
#[test]
fn one_by_one_png() {
    bad_file("one_by_one.png", &["1 x 1", "too small"]);
}
#[test]
fn two_by_two_png() {
    bad_file("two_by_two.png", &["2 x 2", "too small"]);
}
#[test]
fn empty_png() {
    bad_file("empty.png", &["empty"]);
}
#[test]
fn text_named_png() {
    bad_file("not_an_image.png", &[]);
}
#[test]
fn forged_huge_png_header() {
    bad_file("forged_huge.png", &["100000 x 100000"]);
}
/// GDAL decodes a cut-off JPEG with only a warning (grey rows after the cut): a third of
/// the Puget Sound 4k JPEG must be refused, the whole file still loads.
#[test]
fn truncated_jpeg() {
    let s = Scratch::new();
    let whole = Path::new(env!("CARGO_MANIFEST_DIR")).join("../shared/data/puget_sound/ps_height_4k.jpg");
    let bytes = std::fs::read(&whole).unwrap();
    let cut = s.path("cut.jpg");
    std::fs::write(&cut, &bytes[..bytes.len() / 3]).unwrap();
    fails_cleanly(&["render", "--heightmap", cut.to_str().unwrap(), "--size", "64x48"], &["cut.jpg", "truncated"]);
    let copy = s.path("whole.jpg");
    std::fs::write(&copy, &bytes).unwrap();
    let o = Command::new(env!("CARGO_BIN_EXE_vkterrain"))
        .args(["render", "--heightmap", copy.to_str().unwrap(), "--size", "64x48", "--out"])
        .arg(s.path("ok.png"))
        .env("RUST_LOG", "error")
        .output()
        .unwrap();
    assert!(o.status.success(), "the whole JPEG: {}", String::from_utf8_lossy(&o.stderr));
}

#[test]
fn truncated_tiff() {
    bad_file("truncated.tif", &["TIFF"]);
}
#[test]
fn corrupt_tiff() {
    bad_file("corrupt.tif", &["TIFF"]);
}
#[test]
fn nan_in_float_tiff() {
    bad_file("nan.tif", &["column 1, row 1", "NaN"]);
}
#[test]
fn infinity_in_float_tiff() {
    bad_file("infinity.tif", &["column 1, row 2", "inf"]);
}
#[test]
fn raw_size_mismatch() {
    let p = corpus("wrong_size.r16");
    fails_cleanly(
        &["render", "--heightmap", &p, "--raw-size", "20x20"],
        &["wrong_size.r16", "--raw-size 20x20", "800 bytes", "has 200"],
    );
}
#[test]
fn raw_size_for_a_png() {
    fails_cleanly(
        &["render", "--heightmap", &corpus("two_by_two.png"), "--raw-size", "64x64"],
        &["two_by_two.png", "--raw-size", ".r16"],
    );
}

#[test]
fn raw_without_size() {
    let p = corpus("wrong_size.r16");
    fails_cleanly(&["render", "--heightmap", &p], &["wrong_size.r16", "--raw-size"]);
}
#[test]
fn larger_than_max_image_dimension_is_drawn_from_tiles() {
    // A strip longer than the device's largest image (lavapipe: 16384) and 3 samples wide
    // is cut into tiles and drawn from them, not refused and not degraded; without
    // shadows, said so: no lighting map both fits one image and keeps 3 samples across.
    let p = corpus("too_big_for_device.r16");
    let scratch = Scratch::new();
    let png = scratch.path("out.png");
    let args =
        ["render", "--heightmap", &p, "--raw-size", "16385x3", "--size", "64x48", "--out", &png.display().to_string()]
            .map(String::from);
    let out = common::run_bounded(&args, 120);
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert_eq!(out.status.code(), Some(0), "{stderr}");
    let r: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    assert_eq!((r["streamed"].as_bool(), r["degraded"].as_bool()), (Some(true), Some(false)), "{r}");
    assert_eq!(r["gpu"]["lighting"]["shadows"], false, "{r}");
    assert!(stderr.contains("too long and narrow for one lighting map"), "{stderr}");
    assert!(png.exists());
}
#[test]
fn hgt_of_wrong_length() {
    bad_file("short.hgt", &["10000 bytes", "1201 x 1201"]);
}
#[test]
fn hgt_all_voids() {
    bad_file("all_void.hgt", &["void"]);
}
#[test]
fn unknown_extension() {
    bad_file("heights.xyz", &["not a raster I can read", "no GDAL driver recognises it"]);
}
#[test]
fn missing_file() {
    let s = Scratch::new();
    let p = s.path("does_not_exist.png").display().to_string();
    fails_cleanly(&["render", "--heightmap", &p], &["does_not_exist.png", "No such file"]);
}
#[test]
fn directory() {
    let s = Scratch::new();
    let d = s.path("a_directory.png");
    std::fs::create_dir_all(&d).unwrap();
    fails_cleanly(&["render", "--heightmap", d.to_str().unwrap()], &["a_directory.png", "directory"]);
}
#[test]
fn unreadable_file() {
    // Tests often run as root, where permissions do not stop reads: a link to
    // /proc/self/mem reads back an I/O error at offset 0 for anyone.
    let s = Scratch::new();
    let p = s.path("unreadable.png");
    let _ = std::fs::remove_file(&p);
    std::os::unix::fs::symlink("/proc/self/mem", &p).unwrap();
    fails_cleanly(&["render", "--heightmap", p.to_str().unwrap()], &["unreadable.png"]);
}

#[test]
fn bad_options() {
    fails_cleanly(&["render", "--delta", "0"], &["--delta", "greater than 0"]);
    fails_cleanly(&["render", "--delta", "-1"], &["--delta"]);
    // A negative count names its option, as other numbers do (clap alone took "-1" for
    // an unknown option).
    fails_cleanly(&["render", "--traversal-threads", "-1"], &["--traversal-threads"]);
    fails_cleanly(&["stream", "x.pmtiles", "--traversal-threads", "-1"], &["--traversal-threads"]);
    fails_cleanly(&["render", "--block", "10"], &["--block 10", "2^m + 1"]);
    fails_cleanly(&["render", "--size", "0x480"], &["--size", "at least 1"]);
    fails_cleanly(&["render", "--camera", "NaN,1,2"], &["--camera", "finite"]);
    fails_cleanly(&["render", "--fovy", "200"], &["--fovy", "179"]);
    fails_cleanly(&["render", "--sun", "400,10"], &["--sun", "azimuth 400"]);
    fails_cleanly(&["view", "--fog", "-0.001"], &["--fog", "0 or more"]);
    fails_cleanly(&["view", "--fog", "nan"], &["--fog", "finite"]);
    fails_cleanly(&["view", "--frames", "0"], &["--frames", "1 or more"]);
    fails_cleanly(&["bench", "--frames", "0"], &["--frames", "1 or more"]);
    fails_cleanly(&["view", "--screenshot", "shot.txt"], &["--screenshot shot.txt", ".png"]);
    fails_cleanly(&["stream", "--frames", "0"], &["--frames", "1 or more"]);
    fails_cleanly(&["stream", "--validation", "on", "--frames", "1"], &["--validation", "--gpu-mb"]);
    fails_cleanly(&["view", "--resize-at", "2:0x0"], &["--resize-at 2:0x0", "at least 1x1"]);
    // A number is a device index, never part of a name ("LLVM 15.0.6" holds a 5).
    fails_cleanly(&["render", "--gpu", "5"], &["--gpu 5", "no such device"]);
    fails_cleanly(&["render", "--gpu", ""], &["--gpu", "no such device"]);
    fails_cleanly(&["render", "--sun", "90,95"], &["--sun", "elevation 95"]);
    fails_cleanly(&["view", "--sun", "west"], &["--sun", "AZ,EL"]);
    fails_cleanly(&["frobnicate"], &["frobnicate"]);
    fails_cleanly(&["bench", "--error-pacing", "fast"], &["--error-pacing", "'fast'", "one of: auto, paced, free"]);
    fails_cleanly(&["render", "--pixels", "deferrred"], &["--pixels", "one of: deferred, forward"]);
    let s = Scratch::new();
    fails_cleanly(&["render", "--out", &s.path("picture.jpg").display().to_string()], &["--out", ".png"]);
    fails_cleanly(&["errors", "--repeat", "0"], &["--repeat", "1 or more"]);
    let bench_out = s.path("bench-out").display().to_string();
    for lod in ["full", "distance"] {
        fails_cleanly(
            &["bench", "--compare", "--lod", lod, "--out", &bench_out],
            &["--compare", &format!("--lod {lod}")],
        );
    }
    assert!(!std::path::Path::new(&bench_out).exists(), "refused before --out was made");
    let file = s.path("a-file");
    std::fs::write(&file, b"x").unwrap();
    let file = file.display().to_string();
    fails_cleanly(&["quality", "--out", &file], &["--out", "a-file", "not a directory"]);
    fails_cleanly(&["quality", "--poses", "99999999999", "--out", &bench_out], &["--poses", "1 to 10000"]);
    fails_cleanly(&["errors", "--repeat=-1"], &["--repeat", "1 or more"]);
    fails_cleanly(&["render", "--fog", "-1"], &["--fog", "0 or more"]);
    fails_cleanly(&["render", "--background", "-1,0,0"], &["--background"]);
    fails_cleanly(&["render", "--size", "99999999999x1"], &["--size", "width 99999999999 is larger than any image"]);
    fails_cleanly(&["render", "--fog", "nan"], &["--fog", "finite"]);
    for window in ["0,inf", "nan,1", "5,1", "0"] {
        let args = ["timeline", "--trace", "t.json", "--out", "t.png", "--window", window];
        fails_cleanly(&args, &["--window", "finite numbers, FROM < TO"]);
    }
    // Before the device and the generations: a dump that cannot be written fails first.
    let dump = s.path("no-such-dir/errors.f32").display().to_string();
    fails_cleanly(&["errors", "--dump", &dump], &["--dump", "errors.f32"]);
    fails_cleanly(&["render", "--gpu", "no-such-gpu"], &["--gpu no-such-gpu", "no such device"]);
    fails_cleanly(&["render", "--size", "20000x100"], &["--size 20000x100", "maxImageDimension2D"]);
}

/// Sizes no window or swapchain can have: one line and exit 2, never a panic (the
/// window system's limit is checked before the window exists, the device's after).
/// Needs a display (the test command runs under Xvfb).
#[test]
fn view_sizes_beyond_the_limits() {
    fails_cleanly(&["view", "--size", "100000x100000", "--frames", "2"], &["--size 100000x100000", "window"]);
    fails_cleanly(&["view", "--size", "40000x100", "--frames", "2"], &["--size 40000x100", "window"]);
    fails_cleanly(&["view", "--size", "20000x20000", "--frames", "2"], &["--size 20000x20000", "maxImageDimension2D"]);
    fails_cleanly(&["view", "--frames", "2", "--resize-at", "1:20000x100"], &["--resize-at 1", "maxImageDimension2D"]);
}

/// Scales single-precision positions cannot hold (an independent audit found a hang
/// with a 1e35 spike and a silent loss of the bound at 1e17 spacing): one line, exit 2.
#[test]
fn scales_beyond_single_precision() {
    let s = Scratch::new();
    let spike = s.path("spike.f32");
    let mut samples = vec![0f32; 129 * 129];
    samples[65 * 129 + 65] = 1e35;
    std::fs::write(&spike, samples.iter().flat_map(|v| v.to_le_bytes()).collect::<Vec<u8>>()).unwrap();
    let p = spike.to_str().unwrap();
    let raw = ["--raw-size", "129x129", "--spacing", "1", "--height-scale", "1"];
    let flat = s.path("flat.f32");
    std::fs::write(&flat, vec![0u8; 129 * 129 * 4]).unwrap();
    let f = flat.to_str().unwrap();
    // In memory and from its tiles alike.
    for tiles in [&[][..], &["--stream"][..]] {
        let args: Vec<&str> =
            ["render", "--heightmap", p].iter().copied().chain(raw).chain(tiles.iter().copied()).collect();
        fails_cleanly(&args, &["spike.f32", "beyond"]);
        let far = ["render", "--heightmap", f, "--raw-size", "129x129", "--spacing", "1e17", "--height-scale", "1"];
        fails_cleanly(&[&far[..], tiles].concat(), &["flat.f32", "--spacing"]);
        fails_cleanly(&[&["render", "--camera", "1e13,0,0"][..], tiles].concat(), &["camera", "beyond"]);
        fails_cleanly(&[&["render", "--size", "20000x100"][..], tiles].concat(), &["--size", "maxImageDimension2D"]);
    }
}

/// Output paths are checked before any work: a directory, a missing directory, a pipe.
#[test]
fn bad_output_paths_fail_before_the_run() {
    let s = Scratch::new();
    std::fs::create_dir_all(s.path("dir.png")).unwrap();
    let dir = s.path("dir.png").display().to_string();
    let missing = s.path("no/such/dir/x.png").display().to_string();
    fails_cleanly(&["render", "--out", &dir], &["--out", "dir.png", "not a regular file"]);
    fails_cleanly(&["render", "--out", &missing], &["--out", "does not exist"]);
    fails_cleanly(&["view", "--screenshot", &dir], &["--screenshot", "not a regular file"]);
    fails_cleanly(&["view", "--screenshot", &missing], &["--screenshot", "does not exist"]);
    fails_cleanly(&["view", "--record-path", &dir], &["--record-path", "not a regular file"]);
    let same = s.path("same.png").display().to_string();
    fails_cleanly(&["view", "--screenshot", &same, "--trace", &same], &["--trace", "the same file as --screenshot"]);
    let slash = format!("{}/", s.path("new").display());
    fails_cleanly(&["view", "--trace", &slash], &["--trace", "names a directory"]);
    let png_slash = format!("{}/", s.path("new.png").display());
    fails_cleanly(&["render", "--out", &png_slash], &["--out", "names a directory"]);
    // An output never replaces an input.
    std::fs::copy(corpus("two_by_two.png"), s.path("input.png")).unwrap();
    let input = s.path("input.png").display().to_string();
    fails_cleanly(
        &["view", "--heightmap", &input, "--screenshot", &input],
        &["--screenshot", "same file as --heightmap"],
    );
    fails_cleanly(&["render", "--heightmap", &input, "--out", &input], &["--out", "same file as --heightmap"]);
    assert_eq!(std::fs::read(&input).unwrap(), std::fs::read(corpus("two_by_two.png")).unwrap());
    let fifo = s.path("fifo.png");
    assert!(Command::new("mkfifo").arg(&fifo).status().unwrap().success());
    fails_cleanly(&["render", "--out", fifo.to_str().unwrap()], &["--out", "not a regular file"]);
}

/// A FIFO or a device as an input is refused before anything reads it (a read would
/// block forever, with no message): the heightmap, the textures, a bench pose file and a
/// trace to draw; exit 2, one line naming the option or the file.
#[test]
fn inputs_that_are_not_regular_files_are_refused_without_a_hang() {
    let s = Scratch::new();
    let fifo = s.path("fifo.png");
    assert!(Command::new("mkfifo").arg(&fifo).status().unwrap().success());
    let f = fifo.to_str().unwrap();
    let problem = "not a regular file";
    fails_cleanly(&["render", "--heightmap", f], &[f, problem]);
    fails_cleanly(&["render", "--heightmap", "/dev/zero"], &["/dev/zero", problem]);
    fails_cleanly(&["view", "--texture", f, "--frames", "1"], &["--texture", problem]);
    fails_cleanly(&["view", "--detail", f, "--frames", "1"], &["--detail", problem]);
    let out = s.path("bench-out").display().to_string();
    fails_cleanly(&["bench", "--path", f, "--out", &out], &["--path", problem]);
    let png = s.path("t.png").display().to_string();
    fails_cleanly(&["timeline", "--trace", f, "--out", &png], &["--trace", problem]);
}

/// An output path that is a symbolic link is written through: the link stays, the file
/// it names gets the picture (as `cp` does), and no temporary file is left.
#[test]
fn output_through_a_symbolic_link() {
    let s = Scratch::new();
    std::os::unix::fs::symlink("target.png", s.path("link.png")).unwrap();
    let field = s.path("hills.f32");
    let bytes: Vec<u8> = (0..33 * 33).flat_map(|i| (((i % 33) as f32 * 0.3).sin() * 4.0).to_le_bytes()).collect();
    std::fs::write(&field, bytes).unwrap();
    let out = Command::new(env!("CARGO_BIN_EXE_vkterrain"))
        .args(["render", "--heightmap", field.to_str().unwrap(), "--raw-size", "33x33", "--block", "9"])
        .args(["--size", "40x30", "--validation", "on", "--sun", "off", "--out", s.path("link.png").to_str().unwrap()])
        .env("RUST_LOG", "error")
        .output()
        .unwrap();
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    assert!(std::fs::symlink_metadata(s.path("link.png")).unwrap().file_type().is_symlink(), "the link was replaced");
    let img = image::open(s.path("target.png")).expect("the picture is in the file the link names");
    assert_eq!((img.width(), img.height()), (40, 30));
    let names: Vec<String> =
        std::fs::read_dir(s.path("")).unwrap().flatten().map(|e| e.file_name().to_string_lossy().into()).collect();
    assert!(names.iter().all(|n| !n.contains(".partial")), "{names:?}");
}

/// Two runs writing the same output file at once (as a test harness may): both
/// succeed under validation (render fails on any message), the file is a whole PNG, and no temporary file of theirs is left. The race is
/// made certain by a third writer's temporary file already in place under one shared
/// temporary name (a directory, so that writing to it fails): each run must use its own.
#[test]
fn two_renders_to_one_file_both_succeed() {
    let scratch = Scratch::new();
    std::fs::create_dir_all(scratch.path("same.partial.tmp")).unwrap();
    let field = scratch.path("hills.f32");
    let bytes: Vec<u8> = (0..65 * 65).flat_map(|i| (((i % 65) as f32 * 0.2).sin() * 5.0).to_le_bytes()).collect();
    std::fs::write(&field, bytes).unwrap();
    let out = scratch.path("same.png");
    let run = || {
        Command::new(env!("CARGO_BIN_EXE_vkterrain"))
            .args(["render", "--heightmap", field.to_str().unwrap(), "--raw-size", "65x65", "--block", "9"])
            .args(["--size", "64x48", "--validation", "on", "--out", out.to_str().unwrap()])
            .env("RUST_LOG", "error")
            .output()
    };
    let (a, b) = std::thread::scope(|s| {
        let a = s.spawn(run);
        let b = s.spawn(run);
        (a.join().unwrap().unwrap(), b.join().unwrap().unwrap())
    });
    for o in [&a, &b] {
        assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    }
    let img = image::open(&out).expect("a whole PNG");
    assert_eq!((img.width(), img.height()), (64, 48));
    let left: Vec<_> = std::fs::read_dir(scratch.path(""))
        .unwrap()
        .flatten()
        .filter(|e| e.file_name().to_string_lossy().contains(".partial") && e.file_name() != "same.partial.tmp")
        .collect();
    assert!(left.is_empty(), "left {left:?}");
}
