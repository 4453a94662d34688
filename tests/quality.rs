//! `vkterrain quality` on the paper's data: strict mode stays within delta at every
//! setting, paper mode does not, and strict mode buys its guarantee with no more
//! triangles than paper mode at equal audited error.

use std::process::Command;

/// Runs `vkterrain quality` with `--morph on|off`; returns quality.json.
fn quality(morph: &str) -> serde_json::Value {
    let data = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../shared/data/puget_sound/ps_height_1k.png");
    assert!(data.exists(), "{} is missing", data.display());
    let out = std::env::temp_dir().join(format!("vkterrain-quality-{}-{morph}", std::process::id()));
    let o = Command::new(env!("CARGO_BIN_EXE_vkterrain"))
        .args(["quality", "--heightmap", data.to_str().unwrap(), "--poses", "3", "--morph", morph])
        .args(["--out", out.to_str().unwrap()])
        .output()
        .unwrap();
    let read = |name: &str| std::fs::read_to_string(out.join(name));
    let (json, csv, png) = (read("quality.json"), read("quality.csv"), std::fs::metadata(out.join("quality.png")));
    let _ = std::fs::remove_dir_all(&out);
    let stderr = String::from_utf8_lossy(&o.stderr);
    assert!(o.status.success(), "{stderr}");
    // Off a terminal, progress is whole lines, not a line of carriage returns.
    assert!(!stderr.contains('\r'), "{stderr:?}");
    assert!(png.unwrap().len() > 1000, "quality.png is missing or empty");
    assert!(csv.unwrap().starts_with("method,parameter,mean_triangles,audited_max_px,mean_stitch_splits\n"));
    serde_json::from_str(&json.unwrap()).unwrap()
}

/// The selections compared unmorphed (morphing trades part of delta for smoothness, the
/// same for any selection); then with morphing, the same triangles, still within delta.
#[test]
fn quality_curve_on_puget_sound() {
    let q = quality("off");
    let points = q["points"].as_array().unwrap();
    let of = |m: &'static str| points.iter().filter(move |p| p["method"] == m);
    assert_eq!(of("strict").count(), 9);
    for p in of("strict") {
        let (delta, err) = (p["parameter"].as_f64().unwrap(), p["audited_max_px"].as_f64().unwrap());
        assert!(err <= delta * 1.01, "strict at delta {delta}: audited {err}");
    }
    let paper_1 = of("paper").find(|p| p["parameter"] == 1.0).unwrap();
    assert!(paper_1["audited_max_px"].as_f64().unwrap() > 1.01, "paper mode within delta: {paper_1}");
    let ratios = q["strict_over_paper_at_equal_error"].as_array().unwrap();
    assert!(ratios.len() >= 3, "too few comparable settings: {ratios:?}");
    for r in ratios {
        assert!(r["ratio"].as_f64().unwrap() <= 1.0, "strict draws more than paper at equal error: {r}");
    }
    let morphed = quality("on");
    let strict_on: Vec<&serde_json::Value> =
        morphed["points"].as_array().unwrap().iter().filter(|p| p["method"] == "strict").collect();
    assert_eq!(strict_on.len(), of("strict").count(), "strict settings with and without morphing");
    for (on, off) in strict_on.iter().zip(of("strict")) {
        let (delta, err) = (on["parameter"].as_f64().unwrap(), on["audited_max_px"].as_f64().unwrap());
        assert!(err <= delta * 1.01, "strict, morphing, at delta {delta}: audited {err}");
        assert_eq!(on["mean_triangles"], off["mean_triangles"], "morphing changed the selection at delta {delta}");
    }
}
