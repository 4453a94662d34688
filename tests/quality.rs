//! `vkterrain quality` on the paper's data: strict mode stays within delta at every
//! setting, paper mode does not, and strict mode buys its guarantee with no more
//! triangles than paper mode at equal audited error.

use std::process::Command;

#[test]
fn quality_curve_on_puget_sound() {
    let data = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../shared/data/puget_sound/ps_height_1k.png");
    assert!(data.exists(), "{} is missing", data.display());
    let out = std::env::temp_dir().join(format!("vkterrain-quality-{}", std::process::id()));
    let o = Command::new(env!("CARGO_BIN_EXE_vkterrain"))
        .args(["quality", "--heightmap", data.to_str().unwrap(), "--poses", "3", "--out", out.to_str().unwrap()])
        .output()
        .unwrap();
    let read = |name: &str| std::fs::read_to_string(out.join(name));
    let (json, csv, png) = (read("quality.json"), read("quality.csv"), std::fs::metadata(out.join("quality.png")));
    let _ = std::fs::remove_dir_all(&out);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    assert!(png.unwrap().len() > 1000, "quality.png is missing or empty");
    assert!(csv.unwrap().starts_with("method,parameter,mean_triangles,audited_max_px,mean_stitch_splits\n"));
    let q: serde_json::Value = serde_json::from_str(&json.unwrap()).unwrap();
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
}
