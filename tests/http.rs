//! Archives over HTTP range requests (issue 27 item 2's plus), against a server on the
//! loopback address: `check`, `render` and `stream` read an archive from a URL as from
//! a file (the same frame, the same tiles); a missing archive, a server that ignores
//! ranges and a server that starts failing mid-flight give clear errors or degrade.

mod common;

use common::{cli, TempDir};
use std::io::{BufRead, BufReader, Write};
use std::net::TcpListener;
use std::path::PathBuf;
use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::Arc;

/// How the test server behaves.
#[derive(Clone, Copy, PartialEq)]
enum Mode {
    /// Byte ranges, as a web server or an object store serves them.
    Ranges,
    /// The whole file with 200, ranges ignored.
    NoRanges,
    /// Ranges for the first `n` requests, then 500.
    FailAfter(usize),
    /// Ranges, marked gzip-encoded (a misconfigured proxy).
    Encoded,
    /// Ranges, with a total length far past the file's end.
    HugeTotal,
    /// Ranges for the first `n` requests, then no answer at all: each later connection is
    /// held open, unanswered, until the test's process ends (a stalled server).
    StallAfter(usize),
}

/// A one-thread-per-connection HTTP/1.1 server over `root` on 127.0.0.1 (any free
/// port), answering each request then closing the connection. Returns its base URL and
/// the count of requests served.
fn serve(root: PathBuf, mode: Mode) -> (String, Arc<AtomicUsize>) {
    let listener = TcpListener::bind("127.0.0.1:0").unwrap();
    let url = format!("http://{}", listener.local_addr().unwrap());
    let served = Arc::new(AtomicUsize::new(0));
    let count = served.clone();
    std::thread::spawn(move || {
        for stream in listener.incoming().flatten() {
            let (root, count) = (root.clone(), count.clone());
            std::thread::spawn(move || {
                let mut reader = BufReader::new(stream.try_clone().unwrap());
                let mut request = String::new();
                let _ = reader.read_line(&mut request);
                let mut range = None;
                loop {
                    let mut line = String::new();
                    if reader.read_line(&mut line).unwrap_or(0) == 0 || line == "\r\n" {
                        break;
                    }
                    if let Some(r) = line.to_ascii_lowercase().strip_prefix("range: bytes=") {
                        let (a, b) = r.trim().split_once('-').unwrap();
                        range = Some((a.parse::<u64>().unwrap(), b.parse::<u64>().unwrap()));
                    }
                }
                let n = count.fetch_add(1, Ordering::SeqCst);
                let path = request.split_whitespace().nth(1).unwrap_or("/").trim_start_matches('/').to_string();
                let mut out = stream;
                let Ok(body) = std::fs::read(root.join(&path)) else {
                    let _ = write!(out, "HTTP/1.1 404 Not Found\r\nContent-Length: 0\r\nConnection: close\r\n\r\n");
                    return;
                };
                match (mode, range) {
                    (Mode::StallAfter(limit), _) if n >= limit => {
                        let _held = out;
                        loop {
                            std::thread::park();
                        }
                    }
                    (Mode::FailAfter(limit), _) if n >= limit => {
                        let _ = write!(
                            out,
                            "HTTP/1.1 500 Internal Server Error\r\nContent-Length: 0\r\nConnection: close\r\n\r\n"
                        );
                    }
                    (Mode::NoRanges, _) | (_, None) => {
                        let _ = write!(
                            out,
                            "HTTP/1.1 200 OK\r\nContent-Length: {}\r\nConnection: close\r\n\r\n",
                            body.len()
                        );
                        let _ = out.write_all(&body);
                    }
                    (_, Some((a, _))) if a >= body.len() as u64 => {
                        let _ = write!(
                            out,
                            "HTTP/1.1 416 Range Not Satisfiable\r\nContent-Length: 0\r\nConnection: close\r\n\r\n"
                        );
                    }
                    (_, Some((a, b))) => {
                        let b = b.min(body.len() as u64 - 1);
                        let part = &body[a as usize..=b as usize];
                        let total = if mode == Mode::HugeTotal { 1u64 << 50 } else { body.len() as u64 };
                        let coding = if mode == Mode::Encoded { "Content-Encoding: gzip\r\n" } else { "" };
                        let _ = write!(
                            out,
                            "HTTP/1.1 206 Partial Content\r\nContent-Range: bytes {a}-{b}/{total}\r\n{coding}Content-Length: {}\r\nConnection: close\r\n\r\n",
                            part.len()
                        );
                        let _ = out.write_all(part);
                    }
                }
            });
        }
    });
    (url, served)
}

fn prepared(dir: &TempDir) -> PathBuf {
    let archive = dir.path().join("a.pmtiles");
    let o = cli(&["prepare", "--synthetic", "1025", "--out", archive.to_str().unwrap()]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    archive
}

#[test]
fn an_archive_over_http_reads_as_from_the_file() {
    let dir = TempDir::new("http-read");
    let archive = prepared(&dir);
    let (base, served) = serve(dir.path().to_path_buf(), Mode::Ranges);
    let url = format!("{base}/a.pmtiles");
    let json = |o: std::process::Output| -> serde_json::Value {
        assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
        serde_json::from_slice(&o.stdout).unwrap()
    };
    let local = json(cli(&["check", archive.to_str().unwrap()]));
    let remote = json(cli(&["check", &url]));
    assert_eq!(remote["tiles_checked"], local["tiles_checked"]);
    assert_eq!(remote["width"], 1025);
    // One range per tile and a few for the header, directories and the length.
    let tiles = local["tiles_checked"].as_u64().unwrap() as usize;
    assert!(served.load(Ordering::SeqCst) >= tiles, "{} requests for {tiles} tiles", served.load(Ordering::SeqCst));

    let frame = |heightmap: &str, png: &str| {
        let png = dir.path().join(png);
        let o = cli(&[
            "render",
            "--heightmap",
            heightmap,
            "--validation",
            "on",
            "--size",
            "160x120",
            "--out",
            png.to_str().unwrap(),
        ]);
        let j = json(o);
        assert_eq!(j["validation_messages"], 0);
        std::fs::read(png).unwrap()
    };
    assert!(frame(archive.to_str().unwrap(), "local.png") == frame(&url, "remote.png"), "a different frame over HTTP");

    let flight = json(cli(&["stream", &url, "--cache-mb", "16", "--frames", "60", "--fps", "120", "--cold"]));
    assert!(flight["first_failure"].is_null(), "{flight}");
    assert!(flight["stats"]["tiles_loaded"].as_u64().unwrap() > 0, "{flight}");
}

#[test]
fn http_failures_are_clear_or_degrade() {
    let dir = TempDir::new("http-fail");
    prepared(&dir);
    let refused = |args: &[&str], needles: &[&str]| {
        let o = cli(args);
        let e = String::from_utf8_lossy(&o.stderr);
        assert_eq!(o.status.code(), Some(2), "{args:?}: {e}");
        for n in needles {
            assert!(e.contains(n), "{args:?}: '{e}' does not mention '{n}'");
        }
    };
    let (base, _) = serve(dir.path().to_path_buf(), Mode::Ranges);
    let missing = format!("{base}/missing.pmtiles");
    refused(&["check", &missing], &[&missing, "404"]);
    let (plain, _) = serve(dir.path().to_path_buf(), Mode::NoRanges);
    let url = format!("{plain}/a.pmtiles");
    refused(&["check", &url], &[&url, "byte ranges"]);
    let o = cli(&["check", "http://127.0.0.1:9/a.pmtiles"]);
    let e = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(2), "{e}");
    assert_eq!(e.matches("127.0.0.1:9").count(), 1, "the URL once: {e}");
    // Credentials in a URL are never printed.
    let secret = missing.replacen("http://", "http://user:s3cret@", 1);
    let o = cli(&["check", &secret]);
    let e = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(2), "{e}");
    assert!(!e.contains("s3cret") && e.contains("http://***@127.0.0.1"), "{e}");
    // A compressed body is not the range's bytes; a length past the file's end is caught
    // at open, not at the first tile beyond the real end.
    let (encoded, _) = serve(dir.path().to_path_buf(), Mode::Encoded);
    let url = format!("{encoded}/a.pmtiles");
    refused(&["check", &url], &[&url, "encoded (gzip)"]);
    let (huge, _) = serve(dir.path().to_path_buf(), Mode::HugeTotal);
    let url = format!("{huge}/a.pmtiles");
    refused(&["check", &url], &[&url, &format!("length as {} bytes", 1u64 << 50), "416"]);
    // A server that fails after the archive opened: the flight goes on coarser.
    let (flaky, _) = serve(dir.path().to_path_buf(), Mode::FailAfter(12));
    let url = format!("{flaky}/a.pmtiles");
    let o = cli(&["stream", &url, "--cache-mb", "16", "--frames", "40", "--fps", "120"]);
    let e = String::from_utf8_lossy(&o.stderr);
    // Finished, with tiles missing: exit 3, degraded in the JSON, said in one line.
    assert_eq!(o.status.code(), Some(3), "{e}");
    assert!(e.contains("vkterrain: finished degraded: "), "{e}");
    let r: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    assert_eq!(r["degraded"], true, "{r}");
    let failure = r["first_failure"].as_str().unwrap_or_else(|| panic!("no failure: {r}"));
    assert!(failure.contains(&url) && failure.contains("tile ") && failure.contains("500"), "{failure}");
}

/// A server that stops answering while the flight warms up (its reads hang until their
/// time-out, a minute each): Ctrl-C still ends the run at once, 130, with its JSON.
#[test]
fn a_stalled_server_does_not_hold_up_a_stop() {
    let dir = TempDir::new("stall");
    prepared(&dir);
    // The header, the root directory and a few tiles, then silence.
    let (base, served) = serve(dir.path().to_path_buf(), Mode::StallAfter(6));
    let url = format!("{base}/a.pmtiles");
    let args = ["stream", url.as_str(), "--frames", "600", "--cache-mb", "16"];
    // Stopped once a read hangs: more requests were made than are answered.
    let s = common::stop_with_signal(&args, |_| served.load(Ordering::SeqCst) > 6, "INT");
    let err = &s.stderr;
    assert_eq!(s.status.code(), Some(130), "{err}");
    assert!(
        s.after_signal < std::time::Duration::from_secs(10),
        "stopped {:?} after the signal: {err}",
        s.after_signal
    );
    assert!(err.contains("vkterrain: interrupted: "), "{err}");
}

/// One terrain opened three ways (the file, cut into tiles in memory; its archive; that
/// archive over HTTP) is one terrain drawn from tiles: the same blocks, the same
/// triangles, the same frame byte for byte, and the same flight.
#[test]
fn a_file_its_archive_and_its_url_draw_the_same() {
    let dir = TempDir::new("http-three-ways");
    let file = common::data("puget_sound/ps_height_1k.png");
    let archive = dir.path().join("ps.pmtiles");
    let o = cli(&["prepare", file.to_str().unwrap(), "--out", archive.to_str().unwrap()]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let (base, _) = serve(dir.path().to_path_buf(), Mode::Ranges);
    let url = format!("{base}/ps.pmtiles");
    let json = |o: std::process::Output| -> serde_json::Value {
        assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
        serde_json::from_slice(&o.stdout).unwrap()
    };
    let view = ["--stream", "--validation", "on", "--size", "160x120", "--camera", "20000,9000,150000"];
    let mut drawn = Vec::new();
    for (i, source) in [file.to_str().unwrap(), archive.to_str().unwrap(), url.as_str()].into_iter().enumerate() {
        let png = dir.path().join(format!("{i}.png"));
        let mut args = vec!["render", source, "--look-at", "80000,0,80000", "--out", png.to_str().unwrap()];
        args.extend(view);
        let r = json(cli(&args));
        assert_eq!(
            (r["validation_messages"].clone(), r["within_bound"].clone()),
            (0.into(), true.into()),
            "{source}: {r}"
        );
        assert!(r["blocks"].as_u64().unwrap() > 10, "{source}: {r}");
        let mut facts: Vec<serde_json::Value> =
            ["blocks", "triangles", "morphing", "hidden_parts"].iter().map(|k| r[k].clone()).collect();
        facts.push(r["gpu"]["tiles_uploaded"].clone());
        let flight = json(cli(&["stream", source, "--frames", "30", "--fps", "120"]));
        facts.extend(["blocks_per_frame", "morphing_per_frame", "frames_over_bound"].map(|k| flight[k].clone()));
        drawn.push((source, facts, std::fs::read(&png).unwrap()));
    }
    for (source, facts, png) in &drawn[1..] {
        assert_eq!(facts, &drawn[0].1, "{source} against {}", drawn[0].0);
        assert!(png == &drawn[0].2, "{source}: a different frame from {}", drawn[0].0);
    }
}

/// The flags of `render`, `errors`, `bench` and `stream` on each way a terrain comes: a file, its
/// archive, that archive over HTTP, and a terrain larger than one image (a raw strip
/// 16,641 samples long, past lavapipe's 16,384). Each run works, or is refused (exit 2)
/// with a message. A refusal that names the way the terrain is drawn ("streamed", "from
/// tiles", "tiles keep") rather than what the terrain has is a feature tiles lack: there
/// is none. Every run is under validation with no message. Measured: all 160 runs work.
#[test]
fn every_flag_works_on_every_source_or_the_terrain_says_why_not() {
    let dir = TempDir::new("http-flag-walk");
    let file = common::hills_png(dir.path(), 257);
    let archive = dir.path().join("hills.pmtiles");
    let o = cli(&["prepare", file.to_str().unwrap(), "--out", archive.to_str().unwrap()]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let strip = dir.path().join("strip.f32");
    let (w, h) = (16641usize, 300usize);
    let bytes: Vec<u8> =
        (0..w * h).flat_map(|i| (((i % w) as f32 * 0.01).sin() * 50.0 + (i / w) as f32 * 0.1).to_le_bytes()).collect();
    std::fs::write(&strip, bytes).unwrap();
    let (base, _) = serve(dir.path().to_path_buf(), Mode::Ranges);
    let url = format!("{base}/hills.pmtiles");
    let texture = dir.path().join("texture.png");
    image::RgbImage::from_fn(64, 64, |x, z| image::Rgb([(x * 4) as u8, (z * 4) as u8, 90])).save(&texture).unwrap();
    let out = |name: &str| dir.path().join(name).to_str().unwrap().to_string();
    let sources: [(&str, Vec<String>); 4] = [
        ("file", vec![file.to_str().unwrap().into()]),
        ("archive", vec![archive.to_str().unwrap().into()]),
        ("url", vec![url.clone()]),
        ("larger than one image", vec![strip.to_str().unwrap().into(), "--raw-size".into(), "16641x300".into()]),
    ];
    let tex = texture.to_str().unwrap().to_string();
    let render_flags = owned(&[
        &["--heights", "relative"][..],
        &["--voids", "hole"],
        &["--fovy", "45"],
        &["--block", "17"],
        &["--queues", "shared"],
        &["--refresh-at", "0.2"],
        &["--update-share", "0.5"],
        &["--error-pacing", "free"],
        &["--error-mode", "paper"],
        &["--delta", "2"],
        &["--morph", "off"],
        &["--traversal-threads", "2"],
        &["--occlusion", "off"],
        &["--sun", "off"],
        &["--texture", &tex],
        &["--detail", &tex, "--detail-tiling", "8", "--detail-weight", "0.5"],
        &["--lod", "full"],
        &["--lod", "distance"],
        &["--export-mesh", &out("mesh.glb")],
        &["--audit"],
        &["--background", "0.1,0.2,0.3"],
        &["--colour-by-lod"],
        &["--fog", "0.001"],
        &["--shading", "heights"],
        &["--pixels", "forward"],
        &["--raycast", "all"],
        &["--cache-mb", "64"],
        &["--gpu-mb", "64"],
        &["--spacing", "20"],
        &["--height-scale", "0.5"],
        &["--stream"],
    ]);
    let errors_flags =
        owned(&[&["--error-mode", "paper"][..], &["--repeat", "2"], &["--dump", &out("dump.bin")], &["--block", "17"]]);
    let bench_flags = owned(&[&["--compare"][..], &["--popping"], &["--path", "rotate360"]]);
    let stream_flags = owned(&[&["--block", "17"][..], &["--error-mode", "paper"]]);
    let mut runs: Vec<(String, Vec<String>, String)> = Vec::new();
    for (name, source) in &sources {
        for flag in &render_flags {
            let mut args: Vec<String> = ["render"].iter().chain(&["--size", "64x48"]).map(|s| s.to_string()).collect();
            args.extend(source.iter().cloned());
            args.extend(["--validation", "on", "--out"].map(String::from));
            args.push(out(&format!("{}.png", runs.len())));
            args.extend(flag.iter().cloned());
            runs.push((name.to_string(), args, flag[0].clone()));
        }
        for flag in &errors_flags {
            let mut args =
                vec!["errors".to_string(), "--validation".into(), "on".into(), "--size".into(), "64x48".into()];
            args.extend(source.iter().cloned());
            args.extend(flag.iter().cloned());
            runs.push((name.to_string(), args, flag[0].clone()));
        }
        for flag in &stream_flags {
            let mut args: Vec<String> =
                ["stream", "--gpu-mb", "64", "--validation", "on", "--size", "64x48", "--frames", "5", "--fps", "200"]
                    .map(String::from)
                    .to_vec();
            args.extend(source.iter().cloned());
            args.extend(flag.iter().cloned());
            runs.push((name.to_string(), args, flag[0].clone()));
        }
        for flag in &bench_flags {
            let mut args: Vec<String> =
                ["bench", "--validation", "on", "--size", "64x48", "--frames", "3", "--no-fidelity", "--out"]
                    .map(String::from)
                    .to_vec();
            args.push(out(&format!("bench{}", runs.len())));
            args.extend(source.iter().cloned());
            args.extend(flag.iter().cloned());
            runs.push((name.to_string(), args, flag[0].clone()));
        }
    }
    // Two runs at a time: most of a run is setting up, on one core.
    let next = AtomicUsize::new(0);
    let results: std::sync::Mutex<Vec<(usize, std::process::Output)>> = Default::default();
    std::thread::scope(|s| {
        for _ in 0..2 {
            s.spawn(|| loop {
                let i = next.fetch_add(1, Ordering::SeqCst);
                let Some((_, args, _)) = runs.get(i) else { break };
                let args: Vec<&str> = args.iter().map(String::as_str).collect();
                let o = cli(&args);
                results.lock().unwrap().push((i, o));
            });
        }
    });
    let mut results = results.into_inner().unwrap();
    results.sort_by_key(|r| r.0);
    // A refusal that names the way the terrain is drawn rather than what it has.
    let path_words = ["streamed", "from tiles", "tiles keep"];
    let mut path_refusals = std::collections::BTreeSet::new();
    let (mut worked, mut refused) = (0, Vec::new());
    for (i, o) in &results {
        let (source, args, flag) = &runs[*i];
        let what = format!("{source}: vkterrain {}", args.join(" "));
        let err = String::from_utf8_lossy(&o.stderr);
        match o.status.code() {
            Some(0) => {
                worked += 1;
                let json = common::json_in(&String::from_utf8_lossy(&o.stdout));
                let messages = json.get("validation_messages").unwrap_or(&json["gpu"]["validation_messages"]);
                assert_eq!(messages, 0, "{what}: {json}");
            }
            Some(2) => {
                let reason = err.lines().rfind(|l| !l.contains("note:")).unwrap_or_default().to_string();
                if path_words.iter().any(|w| reason.contains(w)) {
                    path_refusals.insert((source.clone(), args[0].clone(), flag.clone()));
                }
                refused.push(format!("{what}\n    {reason}"));
            }
            _ => panic!("{what}: exit {:?}\n{err}", o.status.code()),
        }
    }
    println!("{worked} runs worked; refused:\n{}", refused.join("\n"));
    assert!(path_refusals.is_empty(), "refusals that name the way the terrain is drawn: {path_refusals:?}");
    // None of these terrains gives a reason to refuse any of these flags.
    assert_eq!(worked, runs.len(), "refused:\n{}", refused.join("\n"));
}

/// Each flag set of the walk as owned arguments.
fn owned(sets: &[&[&str]]) -> Vec<Vec<String>> {
    sets.iter().map(|f| f.iter().map(|s| s.to_string()).collect()).collect()
}
