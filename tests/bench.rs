//! A short bench run on a small field writes every documented file with its columns and
//! keys, under validation with zero messages; and a short soak keeps error generations
//! flowing with bounded memory.

mod common;
use common::TempDir;
use std::path::{Path, PathBuf};
use std::process::Command;

/// Writes the small test field into `dir`.
fn small_field(dir: &Path) -> PathBuf {
    let p = dir.join("hills.f32");
    let bytes: Vec<u8> = (0..257 * 257)
        .flat_map(|i| {
            let (x, z) = ((i % 257) as f32, (i / 257) as f32);
            ((x * 0.07).sin() * (z * 0.05).cos() * 40.0 + (x * 0.31).sin() * 3.0).to_le_bytes()
        })
        .collect();
    std::fs::write(&p, bytes).unwrap();
    p
}

/// Starts `vkterrain ARGS --out OUT` (errors only in the log, stdout dropped), with
/// stderr as given: for tests that signal or watch a running bench.
fn spawn(args: &[&str], out: &Path, stderr: std::process::Stdio) -> std::process::Child {
    Command::new(env!("CARGO_BIN_EXE_vkterrain"))
        .args(args)
        .arg("--out")
        .arg(out)
        .env("RUST_LOG", "error")
        .stdout(std::process::Stdio::null())
        .stderr(stderr)
        .spawn()
        .unwrap()
}

/// Runs a bench into `out` (inside a test's TempDir, which also gets the field).
fn bench(out: &Path, extra: &[&str]) -> serde_json::Value {
    let field = small_field(out.parent().unwrap());
    let mut args = vec![
        "bench".to_string(),
        "--heightmap".into(),
        field.display().to_string(),
        "--raw-size".into(),
        "257x257".into(),
        "--spacing".into(),
        "10".into(),
        "--block".into(),
        "9".into(),
        "--validation".into(),
        "on".into(),
        "--out".into(),
        out.display().to_string(),
    ];
    // A small frame unless the test sizes its own.
    if !extra.contains(&"--size") {
        args.extend(["--size".into(), "160x120".into()]);
    }
    args.extend(extra.iter().map(|s| s.to_string()));
    let o = Command::new(env!("CARGO_BIN_EXE_vkterrain")).args(&args).env("RUST_LOG", "error").output().unwrap();
    let stderr = String::from_utf8_lossy(&o.stderr);
    assert!(o.status.success(), "bench failed: {stderr}");
    let summary: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(out.join("summary.json")).unwrap()).unwrap();
    assert_eq!(summary["validation"], true);
    assert_eq!(summary["validation_messages"], 0, "{stderr}");
    summary
}

/// One summary.json schema and one frames.csv header, whichever way a terrain is drawn:
/// a file in memory and the same file drawn from its tiles write the same keys (each
/// filled where it applies: frames over the bound, the tiles' cache and atlas; the
/// in-memory figures such as the readback a generation, the RSS, the generations' order).
#[test]
fn a_bench_in_memory_and_over_tiles_writes_one_schema() {
    let tmp = TempDir::new("bench-schema");
    let (memory, tiles) = (tmp.path().join("memory"), tmp.path().join("tiles"));
    let m = bench(&memory, &["--frames", "3", "--no-fidelity"]);
    let t = bench(&tiles, &["--frames", "3", "--no-fidelity", "--stream"]);
    let keys =
        |v: &serde_json::Value| v.as_object().unwrap().keys().cloned().collect::<std::collections::BTreeSet<_>>();
    let (km, kt) = (keys(&m), keys(&t));
    let (only_m, only_t): (Vec<_>, Vec<_>) = (km.difference(&kt).collect(), kt.difference(&km).collect());
    assert_eq!(km, kt, "only in memory: {only_m:?}; only over tiles: {only_t:?}");
    for (s, streamed) in [(&m, false), (&t, true)] {
        assert_eq!(s["streamed"], streamed, "{s}");
        assert_eq!(s["generations_strictly_increasing"], true, "{s}");
        assert!(s["heightfield_bytes"].as_u64().is_some_and(|b| b > 0), "{s}");
        // Over tiles this one-tile field's blocks are bounded by the tile's summary (the
        // errors activity shades tiles above level 0): no generation, nothing read back.
        let errors = !streamed;
        assert_eq!(s["readback_bytes_per_update"].as_u64().map(|b| b > 0), Some(errors), "{s}");
        assert_eq!(s["mean_blocks_bounded_by_errors"].as_f64().map(|b| b > 0.0), Some(errors), "{s}");
        assert_eq!(s["validation_counted_after_device_destruction"], true, "{s}");
    }
    let header =
        |dir: &Path| std::fs::read_to_string(dir.join("frames.csv")).unwrap().lines().next().unwrap().to_string();
    assert_eq!(header(&memory), header(&tiles));
}

#[test]
fn short_bench_writes_every_file_with_documented_fields() {
    let tmp = TempDir::new("bench");
    let out = tmp.path().join("out");
    let s = bench(&out, &["--path", "paper-flyover", "--frames", "24", "--compare"]);
    let csv = std::fs::read_to_string(out.join("frames.csv")).unwrap();
    let mut lines = csv.lines();
    assert_eq!(
        lines.next().unwrap(),
        "time_s,frame_ms,traverse_ms,gpu_ms,triangles,draw_calls,blocks,error_generation,error_age_frames,\
         error_update_ms,queue_wait_ms,morphing,temporal_rmse,popping,lod_change_rmse,lod_change_over16,occluded,raycast_blocks,raycast_pixels,hidden_parts,\
         over_bound,worst_factor,tiles_held"
    );
    let rows: Vec<Vec<&str>> = lines.map(|l| l.split(',').collect()).collect();
    assert_eq!(rows.len(), 24);
    assert!(rows.iter().all(|r| r.len() == 23));
    // The whole terrain in one image: never over the bound, no tiles.
    assert!(rows.iter().all(|r| r[20..] == ["0", "", ""]));
    // The ray-caster is off by default: no block drawn by it, no ray cast.
    assert!(rows.iter().all(|r| r[17] == "0" && r[18] == "0"));
    assert_eq!(s["mean_raycast_blocks"], 0.0);
    // Without --popping no frame is read back for it.
    assert!(rows.iter().all(|r| r[12..16] == ["", "", "", ""]));
    // Occlusion culling (on by default): blocks left undrawn where it ran, empty where it
    // was paused or skipped; the summary counts the frames it ran on.
    let ran = rows.iter().filter(|r| !r[16].is_empty()).count();
    assert!(rows.iter().all(|r| r[16].is_empty() || r[16].parse::<usize>().is_ok()));
    assert!(ran >= 1, "the first frame always runs the sweep");
    assert_eq!(s["occlusion_culled_frames"], ran);
    // Blocks crossing the image's edge leave their parts outside it undrawn.
    let outside = s["outside_part_share"].as_f64().unwrap();
    assert!(outside > 0.0 && outside < 1.0, "outside_part_share {outside}");
    // Terrain is ahead for the first three quarters of the path (at the far edge the
    // camera looks out past it, as at the end of the paper's Figure 8).
    assert!(rows[..18].iter().all(|r| r[4].parse::<u64>().unwrap() > 0), "frames with terrain ahead draw triangles");
    for key in [
        "avg_fps",
        "median_frame_ms",
        "p99_frame_ms",
        "mean_triangles",
        "mtriangles_per_s",
        "error_updates",
        "median_error_update_ms",
        "median_queue_wait_ms",
        "readback_bytes_per_update",
        "geometry_bytes",
        "heightfield_bytes",
        "queue_mode",
        "device",
        "validation_messages",
        "fidelity",
        "compare",
    ] {
        // Timestamps are optional on a device: their figures may be null.
        let optional = ["median_error_update_ms", "median_queue_wait_ms"].contains(&key);
        assert!(!s[key].is_null() || optional, "summary.json lacks {key}: {s}");
    }
    assert_eq!(s["generations_strictly_increasing"], true);
    assert_eq!(s["error_mode"], "strict");
    // One shared queue: the errors thread paces its submissions, one generation at a time.
    assert_eq!((s["queue_mode"].as_str(), s["most_generations_in_flight"].as_u64()), (Some("shared"), Some(1)));
    assert_eq!((s["pixels"].as_str(), s["shading"].as_str()), (Some("deferred"), Some("gradient-map")));
    assert!(s["error_updates"].as_u64().unwrap() >= 2);
    for run in ["error", "full", "distance", "ceiling"] {
        assert_eq!(s["compare"][run]["frames"], 24, "{run}");
        // Each run begins with one untimed frame, waited for, not among its 24.
        assert!(s["compare"][run]["warmup_ms"].as_f64().is_some_and(|w| w > 0.0), "{run}: {s}");
    }
    // The ceiling's frames beside the error run's, the same columns and as many rows,
    // drawing the same triangles frame by frame.
    let ceiling = std::fs::read_to_string(out.join("ceiling.csv")).unwrap();
    assert_eq!(ceiling.lines().next(), csv.lines().next());
    let ceiling: Vec<Vec<&str>> = ceiling.lines().skip(1).map(|l| l.split(',').collect()).collect();
    assert_eq!(ceiling.len(), rows.len());
    for (c, r) in ceiling.iter().zip(&rows) {
        assert_eq!(c[4], r[4], "the ceiling replays the error run's blocks");
    }
    // LOD selection never draws more than full resolution.
    assert!(s["compare"]["triangles_full_over_error"].as_f64().unwrap() >= 1.0);
    let (median, p99) =
        (s["compare"]["median_excess_over_ceiling_ms"].as_f64(), s["compare"]["p99_excess_over_ceiling_ms"].as_f64());
    assert!(matches!((median, p99), (Some(m), Some(p)) if p >= m), "{median:?} {p99:?}");
    // The stall target: the larger of a quarter of the ceiling's median frame and 1.5x
    // the p99 gap between two ceiling runs, and whether the excess meets it.
    let c = &s["compare"];
    let (gap, target) = (c["p99_ceiling_gap_ms"].as_f64().unwrap(), c["stall_target_ms"].as_f64().unwrap());
    let quarter = 0.25 * c["ceiling"]["median_frame_ms"].as_f64().unwrap();
    assert!((target - quarter.max(1.5 * gap)).abs() < 1e-9, "target {target}, gap {gap}, quarter {quarter}");
    assert_eq!(c["stall_target_met"], serde_json::json!(p99.unwrap() <= target));
    assert_eq!(s["fidelity"].as_array().unwrap().len(), 12);
    let plot = image::open(out.join("plot.png")).unwrap();
    assert_eq!((plot.width(), plot.height()), (960, 640));
    let trace: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(out.join("trace.json")).unwrap()).unwrap();
    let events = trace["traceEvents"].as_array().unwrap();
    let has = |name: &str| events.iter().any(|e| e["name"] == name);
    for name in [
        "generation",
        "submit (errors queue)",
        "submit (draw queue)",
        "observed generation",
        "errors timeline (signalled)",
        "traverse",
    ] {
        assert!(has(name), "trace.json has no '{name}' event");
    }
    // GPU tracks (timestamps placed on the CPU clock): every frame of the error run is a
    // span there, starting no earlier than its submission (within the calibration's
    // uncertainty), and the errors' GPU work is there too.
    let clock = events.iter().find(|e| e["name"] == "gpu_clock").expect("GPU clock metadata");
    let slack = clock["args"]["uncertainty_us"].as_f64().unwrap() + 500.0;
    let gpu_frames: Vec<&serde_json::Value> =
        events.iter().filter(|e| e["ph"] == "X" && e["tid"] == 10 && e["name"] == "error").collect();
    assert_eq!(gpu_frames.len(), 24, "GPU spans of the error run");
    for span in &gpu_frames {
        // The submission began when the draw thread asked for the queue's lock (the
        // `submit` instant is taken after vkQueueSubmit returns, when the GPU may
        // already be running the frame). The error run is the first with this frame.
        let frame = &span["args"]["frame"];
        let submit = events
            .iter()
            .find(|e| e["name"] == "wait (queue lock)" && e["tid"] == 1 && &e["args"]["frame"] == frame)
            .expect("the frame's submission");
        let (ts, at) = (span["ts"].as_f64().unwrap(), submit["ts"].as_f64().unwrap());
        assert!(ts >= at - slack, "frame {frame}: GPU start {ts} before its submission {at}");
    }
    assert!(events.iter().any(|e| e["ph"] == "X" && e["name"] == "error passes"), "no GPU error passes");
    // GPU work and timeline values agree: every generation's passes ended on the GPU
    // before the draw thread observed that generation's timeline value.
    for seen in events.iter().filter(|e| e["name"] == "observed generation") {
        let (g, at) = (&seen["args"]["generation"], seen["ts"].as_f64().unwrap());
        for pass in events.iter().filter(|e| e["name"] == "error passes" && &e["args"]["generation"] == g) {
            let end = pass["ts"].as_f64().unwrap() + pass["dur"].as_f64().unwrap();
            assert!(end <= at + slack, "generation {g}: GPU work ends at {end}, observed at {at}");
        }
    }
    // A flow from each generation used to the frame that took it.
    let ids = |ph: &str| -> Vec<u64> {
        events
            .iter()
            .filter(|e| e["ph"] == ph && e["name"] == "generation")
            .map(|e| e["id"].as_u64().unwrap())
            .collect()
    };
    let (starts, ends) = (ids("s"), ids("f"));
    assert!(!ends.is_empty() && ends.iter().all(|id| starts.contains(id)), "flows: starts {starts:?}, ends {ends:?}");
    // Each arrow points forward: a generation is traced as finished before the draw
    // thread can take it.
    let at = |ph: &str, id: u64| {
        let e = events.iter().find(|e| e["ph"] == ph && e["name"] == "generation" && e["id"] == id).unwrap();
        e["ts"].as_f64().unwrap()
    };
    for &id in &ends {
        assert!(at("f", id) >= at("s", id), "generation {id}: taken at {}, finished at {}", at("f", id), at("s", id));
    }
}

/// `--popping`: every frame of the error run and of the full run is compared with the one
/// before, the excess is the difference, and the LOD change alone is measured from each
/// frame's camera; with morphing on, blocks are drawn part way.
#[test]
fn popping_is_measured_frame_by_frame() {
    let tmp = TempDir::new("popping");
    for morph in ["on", "off"] {
        let out = tmp.path().join(morph);
        let s = bench(&out, &["--frames", "12", "--popping", "--no-fidelity", "--morph", morph]);
        assert_eq!(s["morph"], morph == "on");
        let p = &s["popping"];
        assert_eq!(p["frame_pairs"], 11, "{p}");
        for key in [
            "mean_excess",
            "p99_excess",
            "mean_lod_change_rmse",
            "p99_lod_change_rmse",
            "mean_lod_change_share_over16",
            "p99_lod_change_share_over16",
        ] {
            assert!(p[key].as_f64().is_some_and(|v| v.is_finite()), "popping.{key}: {p}");
        }
        let csv = std::fs::read_to_string(out.join("frames.csv")).unwrap();
        let rows: Vec<Vec<String>> = csv.lines().skip(1).map(|l| l.split(',').map(String::from).collect()).collect();
        let num = |r: &[String], c: usize| r[c].parse::<f64>().ok();
        assert!(rows[0][12..16].iter().all(|c| c.is_empty()), "the first frame has no predecessor");
        for r in &rows[1..] {
            let (t, excess, change) = (num(r, 12).unwrap(), num(r, 13).unwrap(), num(r, 14).unwrap());
            assert!(t >= 0.0 && change >= 0.0 && excess <= t + 1e-3, "{r:?}");
            // A visible jump in a pixel shows in the RMSE: over 16 levels in one channel of
            // a share s of the pixels is at least 17 * sqrt(s / 3).
            let over16 = num(r, 15).unwrap();
            assert!((0.0..=1.0).contains(&over16) && change + 1e-3 >= 17.0 * (over16 / 3.0).sqrt(), "{r:?}");
        }
        let mean: f64 = rows[1..].iter().map(|r| num(r, 13).unwrap()).sum::<f64>() / 11.0;
        assert!((mean - p["mean_excess"].as_f64().unwrap()).abs() < 1e-3, "mean excess {mean} against {p}");
        let morphing: usize = rows.iter().map(|r| r[11].parse::<usize>().unwrap()).sum();
        assert_eq!(morphing > 0, morph == "on", "blocks drawn part way: {morphing}");
    }
}

#[test]
fn short_soak_keeps_generations_flowing() {
    let tmp = TempDir::new("soak");
    let out = tmp.path().join("out");
    // Every frame asks for new data (no refresh rule, no share cap), and the errors
    // thread submits at once (free pacing, as with separate queues): the hand-off is
    // exercised as hard as the errors thread can go, two generations in flight.
    let s = bench(
        &out,
        &[
            "--path",
            "paper-flyover",
            "--frames",
            "400",
            "--no-fidelity",
            "--refresh-at",
            "0",
            "--update-share",
            "1",
            "--error-pacing",
            "free",
        ],
    );
    assert_eq!(s["frames"], 400);
    assert_eq!(s["most_generations_in_flight"], 2, "free pacing, a request every frame");
    assert_eq!(s["generations_strictly_increasing"], true);
    // A fast camera: generations keep coming all along the run (each quarter of the run
    // draws with newer data than the quarter before).
    assert!(s["error_updates"].as_u64().unwrap() >= 40, "{}", s["error_updates"]);
    let csv = std::fs::read_to_string(out.join("frames.csv")).unwrap();
    let gens: Vec<u64> = csv.lines().skip(1).map(|l| l.split(',').nth(7).unwrap().parse().unwrap()).collect();
    let newest: Vec<u64> = gens.chunks(100).map(|q| *q.iter().max().unwrap()).collect();
    assert!(newest.windows(2).all(|w| w[1] > w[0]), "newest generation per quarter: {newest:?}");
    let (a, b) = (s["rss_start_mib"].as_f64().unwrap(), s["rss_end_mib"].as_f64().unwrap());
    assert!(b - a < 64.0, "resident memory grew from {a:.1} to {b:.1} MiB");
}

#[test]
fn ctrl_c_stops_cleanly_and_keeps_what_was_measured() {
    let tmp = TempDir::new("ctrlc");
    let out = tmp.path().join("out");
    let field = small_field(tmp.path());
    let args = ["bench", "--heightmap", field.to_str().unwrap(), "--raw-size", "257x257", "--spacing", "10"];
    let args =
        [&args[..], &["--block", "9", "--size", "160x120", "--frames", "1000000", "--validation", "on"]].concat();
    let mut child = spawn(&args, &out, std::process::Stdio::null());
    // Interrupted once frames of the main run are in its streamed trace (whatever the
    // machine's load), so that there is something to keep.
    let partial = out.join("trace.json.partial");
    let start = std::time::Instant::now();
    while !std::fs::read_to_string(&partial).is_ok_and(|t| t.matches("\"name\":\"error\"").count() >= 3) {
        assert!(child.try_wait().unwrap().is_none(), "bench exited before it was interrupted");
        assert!(start.elapsed() < std::time::Duration::from_secs(120), "bench drew no frame in 120 s");
        std::thread::sleep(std::time::Duration::from_millis(50));
    }
    let killed = Command::new("kill").args(["-INT", &child.id().to_string()]).status().unwrap();
    assert!(killed.success());
    let start = std::time::Instant::now();
    let status = loop {
        if let Some(s) = child.try_wait().unwrap() {
            break s;
        }
        assert!(start.elapsed() < std::time::Duration::from_secs(60), "bench did not stop after Ctrl-C");
        std::thread::sleep(std::time::Duration::from_millis(100));
    };
    assert_eq!(status.code(), Some(130), "interrupted by SIGINT: 128 + 2; {status:?}");
    let summary: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(out.join("summary.json")).unwrap()).unwrap();
    assert_eq!(summary["interrupted"], true);
    assert_eq!(summary["validation_messages"], 0);
    let frames = summary["frames"].as_u64().unwrap();
    assert!(frames > 0 && frames < 1_000_000);
    let rows = std::fs::read_to_string(out.join("frames.csv")).unwrap().lines().count() as u64 - 1;
    assert_eq!(rows, frames);
    assert!(out.join("plot.png").exists() && out.join("trace.json").exists());
}

/// Stopped during a run that --compare adds (here the `--lod full` one, at its third
/// frame): the summary says interrupted and holds no comparison built from the partial
/// run; the main run's results are all there.
#[test]
fn a_compare_stopped_part_way_reports_no_ratios() {
    let tmp = TempDir::new("cmpstop");
    let out = tmp.path().join("out");
    let field = small_field(tmp.path());
    let o = Command::new(env!("CARGO_BIN_EXE_vkterrain"))
        .args(["bench", "--heightmap", field.to_str().unwrap(), "--raw-size", "257x257", "--spacing", "10"])
        .args(["--block", "9", "--size", "160x120", "--frames", "12", "--validation", "on", "--no-fidelity"])
        .args(["--compare", "--inject-fault", "interrupt-full:3", "--out"])
        .arg(&out)
        .env("RUST_LOG", "error")
        .output()
        .unwrap();
    stopped_in_the_full_run(o.status.code(), &String::from_utf8_lossy(&o.stderr), &out);
}

/// A 12-frame `bench --compare` stopped in its `--lod full` run: as by Ctrl-C (130), the
/// summary says interrupted and holds no comparison; the main run's results are all there.
fn stopped_in_the_full_run(code: Option<i32>, stderr: &str, out: &Path) {
    assert_eq!(code, Some(130), "{stderr}");
    assert!(stderr.contains("interrupted: partial results"), "{stderr}");
    let summary: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(out.join("summary.json")).unwrap()).unwrap();
    assert_eq!(summary["interrupted"], true);
    assert!(summary.get("compare").is_none(), "{}", summary["compare"]);
    assert_eq!(summary["frames"], 12);
    assert_eq!(summary["validation_messages"], 0);
    let rows = std::fs::read_to_string(out.join("frames.csv")).unwrap().lines().count();
    assert_eq!(rows, 13);
}

/// Runs a bench with an injected fault; it must exit with 1 (not hang, not panic), one
/// error line naming the stage and the Vulkan result, both threads joined.
fn faulted(fault: &str, needles: &[&str]) {
    faulted_on(&|dir: &Path| small_field_args(dir), fault, needles);
}

/// The small field's arguments (blocks of 9 vertices), the field written into `dir`.
fn small_field_args(dir: &Path) -> Vec<String> {
    let field = small_field(dir).display().to_string();
    ["--raw-size", "257x257", "--spacing", "10", "--block", "9"].iter().fold(vec![field], |mut v, a| {
        v.push(a.to_string());
        v
    })
}

/// A 1025 x 1025 PNG drawn from its tiles (`--stream`; cut into tiles in memory), written
/// into `dir`: enough tiles above level 0 for the errors activity to shade generations.
fn tiled_field_args(dir: &Path) -> Vec<String> {
    let png = common::hills_png(dir, 1025).display().to_string();
    vec![png, "--stream".into()]
}

/// [`faulted`] on the terrain `terrain(dir)` gives.
fn faulted_on(terrain: &dyn Fn(&Path) -> Vec<String>, fault: &str, needles: &[&str]) {
    let tmp = TempDir::new("fault");
    let out = tmp.path().join("out");
    let mut args: Vec<String> = vec!["bench".into()];
    args.extend(terrain(tmp.path()));
    args.extend(
        ["--size", "160x120", "--frames", "200", "--validation", "on", "--inject-fault", fault].map(String::from),
    );
    let args: Vec<&str> = args.iter().map(String::as_str).collect();
    let mut child = spawn(&args, &out, std::process::Stdio::piped());
    let start = std::time::Instant::now();
    while child.try_wait().unwrap().is_none() {
        assert!(start.elapsed() < std::time::Duration::from_secs(60), "{fault}: the run hangs");
        std::thread::sleep(std::time::Duration::from_millis(50));
    }
    let o = child.wait_with_output().unwrap();
    let stderr = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(1), "{fault}: {stderr}");
    assert!(!stderr.contains("panicked"), "{stderr}");
    // The error is the last line (set-up lines come before it).
    let line = stderr
        .lines()
        .rev()
        .find(|l| l.starts_with("vkterrain:") && !l.contains("queue mode") && !l.starts_with("vkterrain: note:"))
        .expect("an error line");
    for n in needles {
        assert!(line.contains(n), "{fault}: '{line}' does not mention '{n}'");
    }
}

/// The faults of the tests above over a terrain drawn from tiles: the errors activity
/// over the atlas losing the device at its second generation, the draw running out of
/// memory, each failing the run with the stage named; a stop during `--compare`'s
/// `--lod full` run reports no ratios; a generation never reached fails the run.
#[test]
fn faults_over_tiles_fail_as_in_memory() {
    faulted_on(&tiled_field_args, "errors-device-lost:2", &["errors activity", "generation 2", "ERROR_DEVICE_LOST"]);
    faulted_on(&tiled_field_args, "draw-out-of-memory:3", &["draw thread, frame 3", "ERROR_OUT_OF_DEVICE_MEMORY"]);
    let tmp = TempDir::new("tilestop");
    let run = |fault: &str, extra: &[&str]| {
        let mut args = tiled_field_args(tmp.path());
        args.extend(["--size", "160x120", "--frames", "12", "--validation", "on"].map(String::from));
        args.extend(extra.iter().map(|e| e.to_string()));
        bench_with_fault(tmp.path(), &args, fault)
    };
    let (code, stderr, out) = run("interrupt-full:3", &["--compare"]);
    stopped_in_the_full_run(code, &stderr, &out);
    let (code, stderr, _) = run("errors-device-lost:100000", &[]);
    assert_eq!(code, Some(2), "{stderr}");
    assert!(stderr.contains("never reached, the run started"), "{stderr}");
}

#[test]
fn device_loss_in_the_errors_activity_fails_cleanly() {
    faulted("errors-device-lost:5", &["errors activity", "generation 5", "ERROR_DEVICE_LOST"]);
}

#[test]
fn out_of_memory_in_the_draw_thread_fails_cleanly() {
    faulted("draw-out-of-memory:3", &["draw thread, frame 3", "ERROR_OUT_OF_DEVICE_MEMORY"]);
}

/// `bench ARGS --inject-fault FAULT --out DIR/out` (the output directory made afresh):
/// its exit code, its stderr and the output directory.
fn bench_with_fault(dir: &Path, args: &[String], fault: &str) -> (Option<i32>, String, PathBuf) {
    let out = dir.join("out");
    let _ = std::fs::remove_dir_all(&out);
    let o = Command::new(env!("CARGO_BIN_EXE_vkterrain"))
        .arg("bench")
        .args(args)
        .args(["--inject-fault", fault, "--out"])
        .arg(&out)
        .env("RUST_LOG", "error")
        .output()
        .unwrap();
    (o.status.code(), String::from_utf8_lossy(&o.stderr).to_string(), out)
}

/// A fault that could never fire is refused before anything runs (exit 2, nothing
/// written), and one that the run never reached fails it: a test that injects a fault
/// must see it happen.
#[test]
fn faults_that_never_fire_are_errors() {
    let tmp = TempDir::new("unfired");
    let field = small_field(tmp.path());
    let run = |fault: &str, extra: &[&str]| {
        let mut args: Vec<String> =
            ["--heightmap", field.to_str().unwrap(), "--raw-size", "257x257", "--spacing", "10"]
                .into_iter()
                .chain(["--block", "9", "--size", "160x120", "--frames", "20", "--no-fidelity"])
                .map(String::from)
                .collect();
        args.extend(extra.iter().map(|e| e.to_string()));
        let (code, stderr, out) = bench_with_fault(tmp.path(), &args, fault);
        assert_eq!(code, Some(2), "{fault}: {stderr}");
        assert!(!stderr.contains("panicked"), "{stderr}");
        (stderr, out.exists())
    };
    for (fault, extra, says) in [
        ("errors-device-lost:0", &[][..], "numbered from 1"),
        ("draw-out-of-memory:20", &[][..], "frames are 0 to 19"),
        ("interrupt-full:3", &[][..], "without --compare or --popping"),
        ("interrupt-full:20", &["--compare"][..], "frames are 0 to 19"),
        ("slow-disk:3", &[][..], "unknown fault"),
        ("errors-device-lost:x", &[][..], "not a whole number"),
    ] {
        let (stderr, wrote) = run(fault, extra);
        assert!(stderr.contains(says), "{fault}: {stderr}");
        assert!(!wrote, "{fault}: refused, yet the output directory was made");
    }
    // Generation 100000 is never started in 20 frames: the run ends, then fails.
    let (stderr, _) = run("errors-device-lost:100000", &[]);
    assert!(stderr.contains("never reached, the run started"), "{stderr}");
}

/// Ctrl-C during set-up (the device is up, no frame drawn yet) still ends the run
/// cleanly with a summary.
#[test]
fn ctrl_c_during_set_up_still_writes_a_summary() {
    use std::io::BufRead;
    let tmp = TempDir::new("ctrlc-setup");
    let out = tmp.path().join("out");
    // The built-in terrain: its set-up after the device (heights, lighting) takes a while.
    let args = ["bench", "--size", "160x120", "--frames", "100000", "--validation", "on"];
    let mut child = spawn(&args, &out, std::process::Stdio::piped());
    let mut lines = std::io::BufReader::new(child.stderr.take().unwrap()).lines();
    let mut seen = Vec::new();
    for line in lines.by_ref() {
        let line = line.unwrap();
        let up = line.contains("queue mode");
        seen.push(line);
        if up {
            break;
        }
    }
    assert!(seen.last().is_some_and(|l| l.contains("queue mode")), "no device line: {seen:?}");
    assert!(Command::new("kill").args(["-INT", &child.id().to_string()]).status().unwrap().success());
    let rest: Vec<String> = lines.map_while(Result::ok).collect();
    let status = child.wait().unwrap();
    assert_eq!(status.code(), Some(130), "exit {status:?}: {seen:?} {rest:?}");
    let summary: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(out.join("summary.json")).unwrap()).unwrap();
    assert_eq!(summary["interrupted"], true);
    assert_eq!(summary["validation_messages"], 0);
    assert!(summary["frames"].as_u64().unwrap() < 100000);
}

/// `--path FILE` replays a pose file (one `cx cy cz lx ly lz` a line): frames = poses;
/// a malformed file is a one-line input error naming the file and line.
#[test]
fn pose_file_replays_as_a_path() {
    let tmp = TempDir::new("poses");
    let dir = tmp.path();
    let poses = dir.join("flight.txt");
    let mut text = String::from("# a short flight over the small field\n\n");
    for i in 0..7 {
        let x = 300.0 + 200.0 * i as f32;
        text += &format!("{x} 400 2400  {} 0 1200\n", x + 100.0);
    }
    std::fs::write(&poses, &text).unwrap();
    let out = dir.join("out");
    let s = bench(&out, &["--path", poses.to_str().unwrap(), "--frames", "99", "--no-fidelity", "--pixels", "forward"]);
    let csv = std::fs::read_to_string(out.join("frames.csv")).unwrap();
    assert_eq!(s["frames"], 7);
    assert_eq!(s["pixels"], "forward");
    assert_eq!(csv.lines().count(), 1 + 7);
    assert_eq!(s["path"], poses.to_str().unwrap());
    assert!(csv.lines().skip(1).all(|l| l.split(',').nth(4).unwrap().parse::<u64>().unwrap() > 0));

    let bad = dir.join("bad.txt");
    std::fs::write(&bad, "1 2 3 4 5 6\n1 2 3 4 five 6\n").unwrap();
    let o = Command::new(env!("CARGO_BIN_EXE_vkterrain"))
        .args(["bench", "--path", bad.to_str().unwrap(), "--out", out.to_str().unwrap()])
        .output()
        .unwrap();
    let stderr = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(2), "{stderr}");
    assert!(stderr.contains("bad.txt:2:"), "{stderr}");
}

/// Textures need no window: `render` drapes `--texture` and `--detail` (the picture
/// changes, and differs again with the detail blended in), and a short `bench` draws
/// with them; zero validation messages throughout.
#[test]
fn render_and_bench_take_textures_headless() {
    let tmp = TempDir::new("textured");
    let height = common::data("puget_sound/ps_height_1k.png");
    let texture = common::data("puget_sound/ps_texture_1k.png");
    let (h, t) = (height.to_str().unwrap(), texture.to_str().unwrap());
    let render = |name: &str, extra: &[&str]| -> (serde_json::Value, image::RgbaImage) {
        let out = tmp.path().join(name);
        let o = Command::new(env!("CARGO_BIN_EXE_vkterrain"))
            .args(["render", "--heightmap", h, "--size", "160x120", "--validation", "on", "--out"])
            .arg(&out)
            .args(extra)
            .env("RUST_LOG", "error")
            .output()
            .unwrap();
        assert!(o.status.success(), "{extra:?}: {}", String::from_utf8_lossy(&o.stderr));
        let json: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
        assert_eq!(json["validation_messages"], 0, "{extra:?}");
        (json, image::open(&out).unwrap().to_rgba8())
    };
    let mean_difference = |a: &image::RgbaImage, b: &image::RgbaImage| {
        assert_eq!(a.dimensions(), b.dimensions());
        let sum: u64 =
            a.pixels().zip(b.pixels()).map(|(p, q)| (0..3).map(|c| p[c].abs_diff(q[c]) as u64).sum::<u64>()).sum();
        sum as f64 / (3 * a.width() * a.height()) as f64
    };
    let (_, bare) = render("bare.png", &[]);
    let (_, textured) = render("textured.png", &["--texture", t]);
    let (_, detailed) = render("detailed.png", &["--texture", t, "--detail", t, "--detail-weight", "0.5"]);
    let d1 = mean_difference(&bare, &textured);
    let d2 = mean_difference(&textured, &detailed);
    assert!(d1 > 5.0, "the texture changed the picture by only {d1:.2} levels");
    assert!(d2 > 0.5, "the detail texture changed the picture by only {d2:.2} levels");
    let out = tmp.path().join("bench");
    let o = Command::new(env!("CARGO_BIN_EXE_vkterrain"))
        .args(["bench", "--heightmap", h, "--texture", t, "--detail", t, "--frames", "6", "--size", "160x120"])
        .args(["--validation", "on", "--no-fidelity", "--out"])
        .arg(&out)
        .env("RUST_LOG", "error")
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let summary: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(out.join("summary.json")).unwrap()).unwrap();
    assert_eq!(summary["frames"], 6);
    assert_eq!(summary["validation_messages"], 0);
}

/// `--raycast all`: the ray-cast blocks and the rays they cast are counted per frame and
/// in the summary, and the frames pass validation (the `bench` helper fails on any message).
#[test]
fn bench_counts_ray_cast_blocks_and_rays() {
    let tmp = TempDir::new("bench-raycast");
    let out = tmp.path().join("out");
    let s = bench(&out, &["--frames", "6", "--no-fidelity", "--morph", "off", "--raycast", "all"]);
    let csv = std::fs::read_to_string(out.join("frames.csv")).unwrap();
    let rows: Vec<Vec<String>> = csv.lines().skip(1).map(|l| l.split(',').map(String::from).collect()).collect();
    assert_eq!(rows.len(), 6);
    let blocks: u64 = rows.iter().map(|r| r[17].parse::<u64>().unwrap()).sum();
    let pixels: f64 = rows.iter().map(|r| r[18].parse::<f64>().unwrap()).sum();
    assert!(blocks > 0 && pixels > 0.0, "{blocks} blocks, {pixels} pixels");
    assert!((s["mean_raycast_blocks"].as_f64().unwrap() - blocks as f64 / 6.0).abs() < 1e-9);
    // A ray-cast block keeps only its outer ring of quads as triangles: with block side 9
    // that is 28 quads of 64; the others draw 128 less 8 for each part left out (16 parts
    // of 2 x 2 quads).
    let tris: u64 = rows.iter().map(|r| r[4].parse::<u64>().unwrap()).sum();
    let all_blocks: u64 = rows.iter().map(|r| r[6].parse::<u64>().unwrap()).sum();
    let hidden: u64 = rows.iter().map(|r| r[19].parse::<u64>().unwrap()).sum();
    assert!(hidden > 0, "no part left out: the check below would not see them counted");
    assert_eq!(tris, (all_blocks - blocks) * 128 - hidden * 8 + blocks * 56);
}

/// `avg_fps` counts the GPU work of the frames still in flight when the run ends: a
/// one-frame run's wall time holds its frame's CPU time and its GPU span (timestamps
/// inside the run), not its CPU time alone (an adversarial review found 1248 fps reported
/// for a frame whose GPU work took 38.9 ms). The frame is large, so that its GPU work
/// outlasts its CPU work: the old formula then fails. (Asserting CPU + half the GPU time
/// failed on lavapipe, whose GPU work overlaps the frame's own CPU work.)
#[test]
fn a_short_runs_fps_includes_the_gpu_work_in_flight() {
    let tmp = TempDir::new("bench-short");
    let out = tmp.path().join("out");
    let s = bench(&out, &["--frames", "1", "--no-fidelity", "--size", "1920x1080"]);
    let csv = std::fs::read_to_string(out.join("frames.csv")).unwrap();
    let row: Vec<f64> = csv.lines().nth(1).unwrap().split(',').take(4).map(|v| v.parse().unwrap()).collect();
    let (frame_ms, gpu_ms) = (row[1], row[3]);
    let wall_ms = 1e3 / s["avg_fps"].as_f64().unwrap();
    assert!(gpu_ms > 0.0, "{csv}");
    assert!(gpu_ms > 1.5 * frame_ms, "the frame's GPU work does not outlast its CPU work: {csv}");
    assert!(wall_ms >= frame_ms.max(gpu_ms), "wall {wall_ms} ms for a frame of {frame_ms} ms CPU, {gpu_ms} ms GPU");
}
