//! Exit codes a script can trust: a run stopped by SIGINT or SIGTERM ends with 128 + the
//! signal (130, 143), after writing what it had measured, with `"interrupted": true` in
//! its JSON; a run that finished with tiles missing ends with 3 (`"degraded": true`).
//! `bench`, `stream` and `view` here; `prepare` (which leaves no partial archive) in
//! tests/archive.rs; degraded flights in tests/stream.rs and tests/http.rs.

mod common;

use common::{cli, hills_png, json_in, signal_code, stop_with_signal, TempDir};

#[test]
fn bench_stopped_by_a_signal_writes_its_partial_results_and_exits_128_plus_the_signal() {
    for signal in ["INT", "TERM"] {
        let tmp = TempDir::new("bench-signal");
        let field = hills_png(tmp.path(), 257);
        let out = tmp.path().join("out");
        let args = [
            "bench",
            field.to_str().unwrap(),
            "--size",
            "96x64",
            "--frames",
            "1000000",
            "--no-fidelity",
            "--out",
            out.to_str().unwrap(),
        ];
        let s = stop_with_signal(&args, |l| l.is_some_and(|l| l.contains("queue mode")), signal);
        assert_eq!(s.status.code(), Some(signal_code(signal)), "SIG{signal}: {}", s.stderr);
        assert!(s.stderr.contains("vkterrain: interrupted: partial results in"), "{}", s.stderr);
        let summary = json_in(&std::fs::read_to_string(out.join("summary.json")).unwrap());
        assert_eq!(summary["interrupted"], true, "{summary}");
        assert_eq!(summary["degraded"], false, "{summary}");
        assert!(summary["frames"].as_u64().unwrap() < 1_000_000);
        assert!(out.join("frames.csv").exists());
    }
}

#[test]
fn stream_stopped_by_a_signal_reports_the_frames_flown_and_exits_128_plus_the_signal() {
    let tmp = TempDir::new("stream-signal");
    let archive = tmp.path().join("a.pmtiles");
    let o = cli(&["prepare", "--synthetic", "513", "--out", archive.to_str().unwrap()]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    for signal in ["INT", "TERM"] {
        // 10 minutes of flight at 30 fps: only the signal ends it.
        let args = ["stream", archive.to_str().unwrap(), "--frames", "18000", "--cache-mb", "16"];
        let s = stop_with_signal(&args, |l| l.is_some_and(|l| l.contains("vkterrain: streaming")), signal);
        assert_eq!(s.status.code(), Some(signal_code(signal)), "SIG{signal}: {}", s.stderr);
        let r = json_in(&s.stdout);
        assert_eq!(r["interrupted"], true, "{r}");
        assert_eq!(r["degraded"], false, "{r}");
        assert!(r["frames"].as_u64().unwrap() < 18000, "{r}");
        assert!(s.stderr.contains("vkterrain: interrupted: "), "{}", s.stderr);
    }
}

/// A flight drawn on the GPU with `--out`, over a file cut into tiles, stopped before its
/// first frame (while the lighting map is made): its JSON and 128 + the signal, and no
/// picture, partial or whole (it used to panic writing an empty one, leaving a partial
/// file).
#[test]
fn stream_stopped_before_its_first_frame_writes_no_picture() {
    let tmp = TempDir::new("stream-signal-out");
    let field = hills_png(tmp.path(), 1025);
    let out = tmp.path().join("out");
    std::fs::create_dir(&out).unwrap();
    let png = out.join("last.png");
    let args = ["stream", field.to_str().unwrap(), "--frames", "18000", "--gpu-mb", "16", "--size", "64x48"];
    let args = [&args[..], &["--validation", "on", "--out", png.to_str().unwrap()]].concat();
    let s = stop_with_signal(&args, |l| l.is_some_and(|l| l.contains("vkterrain: atlas of")), "TERM");
    assert_eq!(s.status.code(), Some(143), "{}", s.stderr);
    let r = json_in(&s.stdout);
    assert_eq!(r["interrupted"], true, "{r}");
    assert!(!s.stderr.contains("panicked"), "{}", s.stderr);
    let left: Vec<_> = std::fs::read_dir(&out).unwrap().flatten().map(|e| e.file_name()).collect();
    assert!(left.is_empty(), "left in --out's folder: {left:?}");
}

#[test]
fn view_stopped_by_a_signal_prints_its_figures_and_exits_128_plus_the_signal() {
    assert!(std::env::var_os("DISPLAY").is_some(), "needs a display: run under xvfb-run (tools/test.sh does)");
    let tmp = TempDir::new("view-signal");
    let field = hills_png(tmp.path(), 257);
    // In memory, and the same terrain prepared and drawn from its archive.
    let archive = tmp.path().join("hills.pmtiles");
    let o = cli(&["prepare", field.to_str().unwrap(), "--out", archive.to_str().unwrap()]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    for (terrain, streamed) in [(&field, &[][..]), (&archive, &["--stream"][..])] {
        for signal in ["INT", "TERM"] {
            let run = format!("{}-{signal}", streamed.len());
            let poses = tmp.path().join(format!("poses-{run}.txt"));
            let counter = tmp.path().join(format!("frames-{run}.txt"));
            let mut args = vec!["view", terrain.to_str().unwrap(), "--size", "160x120", "--frames", "100000"];
            args.extend(streamed);
            args.extend(["--record-path", poses.to_str().unwrap(), "--validation", "on"]);
            args.extend(["--frame-counter", counter.to_str().unwrap()]);
            // Stopped once it has drawn a few frames.
            let drawn = || std::fs::read_to_string(&counter).ok().and_then(|t| t.trim().parse::<u64>().ok());
            let s = stop_with_signal(&args, |_| drawn().is_some_and(|n| n >= 3), signal);
            assert_eq!(s.status.code(), Some(signal_code(signal)), "{terrain:?} SIG{signal}: {}", s.stderr);
            let r = json_in(&s.stdout);
            assert_eq!(r["interrupted"], true, "{r}");
            assert_eq!(r["degraded"], false, "{r}");
            assert_eq!(r["validation_messages"], 0, "{r}");
            // The flight so far is kept: one pose a frame drawn.
            let recorded = std::fs::read_to_string(&poses).unwrap();
            let n = recorded.lines().filter(|l| !l.starts_with('#')).count() as u64;
            assert!(n >= 3, "{recorded}");
            assert_eq!(n, r["frames"].as_u64().unwrap(), "{recorded}");
        }
    }
}
