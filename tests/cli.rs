//! The command line as a newcomer meets it: the README's run command works from the
//! user's own folder (relative inputs and outputs mean what was typed), every subcommand
//! takes its terrain as TERRAIN or as `--heightmap FILE` alike, a misplaced input gets the
//! right form in its message, and `render`'s JSON says whether rays were cast.

mod common;

use common::{cli, data, hills_png, json_in, TempDir};
use std::path::Path;
use std::process::Command;

fn json(o: &std::process::Output) -> serde_json::Value {
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    json_in(&String::from_utf8_lossy(&o.stdout))
}

/// The README's own-DEM command as a user types it: a DEM copied into an empty folder
/// outside the clone, `bash CLONE/tools/run.sh render mydem.png --out view.png` run from
/// there; the picture lands in that folder, nothing in the clone.
#[test]
fn the_run_command_works_from_the_users_own_folder() {
    let home = TempDir::new("newcomer");
    std::fs::copy(data("puget_sound/ps_height_1k.png"), home.path().join("mydem.png")).unwrap();
    let clone = Path::new(env!("CARGO_MANIFEST_DIR"));
    // The build the tests run from (target/debug/vkterrain): the script builds nothing new.
    let target = Path::new(env!("CARGO_BIN_EXE_vkterrain")).parent().and_then(Path::parent).unwrap();
    let mut child = Command::new("bash")
        .arg(clone.join("tools/run.sh"))
        .args(["render", "mydem.png", "--size", "160x90", "--out", "view.png"])
        .current_dir(home.path())
        .env("CARGO_TARGET_DIR", target)
        .stdout(std::process::Stdio::piped())
        .stderr(std::process::Stdio::piped())
        .spawn()
        .unwrap();
    let started = std::time::Instant::now();
    // Polling the child's state (not a fixed sleep standing in for synchronisation).
    while child.try_wait().unwrap().is_none() {
        if started.elapsed().as_secs() > 600 {
            let _ = child.kill();
            panic!("tools/run.sh still running after 600 s");
        }
        std::thread::sleep(std::time::Duration::from_millis(50));
    }
    let o = child.wait_with_output().unwrap();
    let r = json(&o);
    assert_eq!(r["samples"], serde_json::json!([1025, 1025]), "{r}");
    assert!(home.path().join("view.png").is_file(), "the picture is not in the user's folder");
    assert!(!clone.join("view.png").exists(), "the picture landed in the clone");
}

/// TERRAIN and `--heightmap FILE` mean the same in every subcommand: the same frame from
/// `render`, the same archive checked and flown; both at once is refused naming both.
#[test]
fn every_subcommand_takes_its_terrain_positionally_or_as_heightmap() {
    let tmp = TempDir::new("forms");
    let field = hills_png(tmp.path(), 129);
    let f = field.to_str().unwrap();
    let render = |form: &[&str], out: &str| {
        let out = tmp.path().join(out);
        let args = [&["render"][..], form, &["--size", "96x64", "--validation", "on", "--out", out.to_str().unwrap()]];
        let r = json(&cli(&args.concat()));
        (r["triangles"].clone(), r["blocks"].clone(), std::fs::read(out).unwrap())
    };
    assert_eq!(render(&[f], "a.png"), render(&["--heightmap", f], "b.png"));
    let o = cli(&["render", f, "--heightmap", f]);
    let e = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(2), "{e}");
    assert!(e.contains("--heightmap") && e.contains("TERRAIN"), "{e}");
    // prepare, check and stream, with --heightmap as the drawing commands spell it.
    let archive = tmp.path().join("hills.pmtiles");
    let a = archive.to_str().unwrap();
    assert!(cli(&["prepare", "--heightmap", f, "--out", a]).status.success());
    let checked = [json(&cli(&["check", a])), json(&cli(&["check", "--heightmap", a]))];
    assert_eq!(checked[0]["tiles_checked"], checked[1]["tiles_checked"]);
    assert!(checked[0]["tiles_checked"].as_u64().unwrap() > 0, "{}", checked[0]);
    let flown = |form: &[&str]| json(&cli(&[&["stream"][..], form, &["--frames", "3", "--fps", "300"]].concat()));
    assert_eq!(flown(&[a])["frames"], 3);
    assert_eq!(flown(&["--heightmap", a])["frames"], 3);
    // Any terrain flies: the file itself and the built-in terrain, cut into tiles.
    assert_eq!(flown(&[f])["blocks_per_frame"], flown(&[a])["blocks_per_frame"]);
    assert_eq!(flown(&[])["frames"], 3);
    // An archive's frame declared beyond what single precision draws is refused as a
    // file's is (it drew frames of NaN), naming the options.
    for declared in [["--spacing", "1e30"], ["--height-scale", "1e12"]] {
        let o = cli(&[&["stream", a, "--frames", "1"][..], &declared].concat());
        let e = String::from_utf8_lossy(&o.stderr);
        assert_eq!(o.status.code(), Some(2), "{declared:?}: {e}");
        assert!(e.contains(declared[0]) && e.contains("1e12"), "{declared:?}: {e}");
    }
}

/// A second terrain where one goes gets the right form in its one-line message (exit 2),
/// not clap's bare "unexpected argument".
#[test]
fn a_misplaced_input_gets_the_right_form() {
    let tmp = TempDir::new("misplaced");
    let field = hills_png(tmp.path(), 129);
    let f = field.to_str().unwrap();
    for (args, form) in [
        (vec!["render", f, f], "`vkterrain render FILE` or `vkterrain render --heightmap FILE`"),
        (vec!["stream", f, f], "`vkterrain stream FILE` or `vkterrain stream --heightmap FILE`"),
        (vec!["check", f, f], "`vkterrain check FILE` or `vkterrain check --heightmap FILE`"),
        (vec![f, f], "`vkterrain view FILE` or `vkterrain render FILE`"),
        (vec!["timeline", f], "`vkterrain timeline --trace FILE --out FILE.png`"),
    ] {
        let o = cli(&args);
        let e = String::from_utf8_lossy(&o.stderr);
        assert_eq!(o.status.code(), Some(2), "{args:?}: {e}");
        assert_eq!(e.lines().count(), 1, "{args:?}: {e}");
        assert!(e.contains("did you mean") && e.contains(form), "{args:?}: {e}");
    }
}

/// `render --raycast all` says in its JSON that rays were cast, and how many blocks they
/// drew; the default casts none and says so.
#[test]
fn render_says_whether_blocks_were_ray_cast() {
    let tmp = TempDir::new("raycast");
    let field = hills_png(tmp.path(), 129);
    let out = tmp.path().join("r.png");
    let base =
        ["render", field.to_str().unwrap(), "--size", "96x64", "--validation", "on", "--out", out.to_str().unwrap()];
    let plain = json(&cli(&base));
    assert_eq!(plain["raycast"], "off", "{plain}");
    assert_eq!(plain["raycast_blocks"], 0, "{plain}");
    let cast = json(&cli(&[&base[..], &["--raycast", "all"]].concat()));
    assert_eq!(cast["raycast"], "all", "{cast}");
    assert!(cast["raycast_blocks"].as_u64().unwrap() > 0, "{cast}");
    // A view where every block morphs or meets a coarser one casts none, and says why.
    let ps = data("puget_sound/ps_height_1k.png");
    let o =
        cli(&["render", ps.to_str().unwrap(), "--size", "320x180", "--raycast", "all", "--out", out.to_str().unwrap()]);
    let none = json(&o);
    assert_eq!(none["raycast_blocks"], 0, "{none}");
    let e = String::from_utf8_lossy(&o.stderr);
    assert!(e.contains("--raycast all: no block of this view was ray-cast: a block is cast only when"), "{e}");
}

/// A negative value where a positive one goes names its option and the rule (clap would
/// take `-10` for an unknown flag).
#[test]
fn a_negative_value_is_refused_naming_its_option() {
    for (flag, value) in [
        ("--fovy", "-10"),
        ("--spacing", "-5"),
        ("--height-scale", "-1"),
        ("--refresh-at", "-1"),
        ("--size", "-160x120"),
        ("--block", "-33"),
        ("--cache-mb", "-1"),
    ] {
        let o = cli(&["render", flag, value, "--out", "never.png"]);
        let e = String::from_utf8_lossy(&o.stderr);
        assert_eq!(o.status.code(), Some(2), "{flag} {value}: {e}");
        assert_eq!(e.lines().count(), 1, "{e}");
        assert!(e.contains(flag) && e.contains(value) && !e.contains("unexpected argument"), "{e}");
    }
}

/// Standard output that cannot be written (a reader that went away, a full disk) ends
/// the run with exit code 1 and one line saying so, never a panic (101).
#[test]
fn an_unwritable_standard_output_is_an_error_not_a_panic() {
    let tmp = TempDir::new("stdout");
    let archive = tmp.path().join("a.pmtiles");
    assert!(cli(&["prepare", "--synthetic", "129", "--out", archive.to_str().unwrap()]).status.success());
    let run = |stdout: std::process::Stdio| {
        let mut child = Command::new(env!("CARGO_BIN_EXE_vkterrain"))
            .args(["check", archive.to_str().unwrap()])
            .stdout(stdout)
            .stderr(std::process::Stdio::piped())
            .spawn()
            .unwrap();
        // A pipe whose reading end is closed before anything is written: EPIPE.
        drop(child.stdout.take());
        child.wait_with_output().unwrap()
    };
    let full = || std::fs::OpenOptions::new().write(true).open("/dev/full").unwrap();
    for (what, o) in [("closed pipe", run(std::process::Stdio::piped())), ("full disk", run(full().into()))] {
        let e = String::from_utf8_lossy(&o.stderr);
        assert_eq!(o.status.code(), Some(1), "{what}: {e}");
        assert!(e.contains("vkterrain: writing to standard output: "), "{what}: {e}");
        assert!(!e.contains("panicked"), "{what}: {e}");
    }
    // Standard error on a full disk: no message can be written, the code still says what
    // happened (1: the notes could not be written; 2: a bad input), never 101.
    let quiet = |args: &[&str]| {
        let o = Command::new(env!("CARGO_BIN_EXE_vkterrain")).args(args).stderr(full()).output().unwrap();
        o.status.code()
    };
    assert_eq!(quiet(&["check", archive.to_str().unwrap()]), Some(1));
    assert_eq!(quiet(&["render", "missing.png", "--out", "never.png"]), Some(2));
}

/// An output the timeline cannot write is a bad option (exit 2), named before any work.
#[test]
fn timeline_refuses_an_output_it_cannot_write() {
    let tmp = TempDir::new("timeline");
    let trace = tmp.path().join("t.json");
    std::fs::write(&trace, r#"{"traceEvents":[]}"#).unwrap();
    for out in [tmp.path().join("missing/t.png"), tmp.path().to_path_buf()] {
        let o = cli(&["timeline", "--trace", trace.to_str().unwrap(), "--out", out.to_str().unwrap()]);
        let e = String::from_utf8_lossy(&o.stderr);
        assert_eq!(o.status.code(), Some(2), "{e}");
        assert!(e.starts_with("vkterrain: --out ") && e.lines().count() == 1, "{e}");
    }
}

/// A flag has one meaning everywhere: its help reads the same in every subcommand that
/// takes it; and a subcommand does not take a flag that means nothing to it (exit 2,
/// naming the flag).
#[test]
fn a_flag_means_one_thing_and_only_where_it_means_something() {
    let help = |sub: &str| {
        let o = cli(&[sub, "--help"]);
        assert!(o.status.success(), "{sub} --help");
        String::from_utf8(o.stdout).unwrap()
    };
    // The flag's paragraph: from its line to the next flag's.
    let paragraph = |text: &str, flag: &str| -> Option<String> {
        let start = text.lines().position(|l| l.trim_start().starts_with(&format!("{flag} ")))?;
        let rest: Vec<&str> = text.lines().skip(start + 1).take_while(|l| !l.trim_start().starts_with('-')).collect();
        Some(rest.join("\n"))
    };
    let takes = [
        ("--delta", &["render", "view", "bench", "stream"][..]),
        ("--morph", &["render", "view", "bench", "stream", "quality"]),
        ("--traversal-threads", &["render", "view", "bench", "stream"]),
        ("--validation", &["render", "view", "bench", "errors", "stream"]),
        ("--block", &["render", "view", "bench", "errors", "quality"]),
        ("--size", &["render", "view", "bench", "errors", "quality"]),
        ("--spacing", &["render", "view", "bench", "errors", "quality", "stream", "prepare"]),
    ];
    for (flag, subs) in takes {
        let texts: Vec<(&str, String)> = subs
            .iter()
            .map(|s| (*s, paragraph(&help(s), flag).unwrap_or_else(|| panic!("{s} does not take {flag}"))))
            .collect();
        for (sub, text) in &texts[1..] {
            assert_eq!(text, &texts[0].1, "{flag}: {sub}'s help differs from {}'s", texts[0].0);
        }
    }
    for (sub, flags) in [
        (
            "errors",
            &["--sun", "off", "--occlusion", "off", "--morph", "off", "--delta", "2", "--refresh-at", "0.1"][..],
        ),
        (
            "quality",
            &["--validation", "on", "--camera", "1,2,3", "--error-mode", "paper", "--delta", "2", "--sun", "off"],
        ),
    ] {
        for pair in flags.chunks(2) {
            let o = cli(&[&[sub][..], pair].concat());
            let e = String::from_utf8_lossy(&o.stderr);
            assert_eq!(o.status.code(), Some(2), "{sub} {pair:?}: {e}");
            assert!(e.contains(pair[0]) && e.contains("unexpected"), "{sub} {pair:?}: {e}");
        }
    }
}
