//! `vkterrain quality`: what the method buys. For the bench path's poses it sweeps delta
//! (strict and paper modes) and the distance factor (distance LOD), and reports, per
//! setting, the triangles drawn against the audited maximum screen-space error (SPEC
//! section 7). Plain Rust on the CPU: the error data comes from the reference that the
//! GPU matches texel for texel (tests/gpu_errors.rs), the audit from `audit`.

use crate::app::cli::{BlockArg, FrustumArgs, InputError, MorphArg, TerrainArgs};
use crate::app::outputs::{plot_font, write_atomic};
use crate::app::paths::{path_camera, CameraPath};
use crate::lod::audit::audit;
use crate::lod::block::BlockLayout;
use crate::lod::gie::{block_errors, group_errors, ErrorMode, ErrorParams};
use crate::lod::pyramid::MinMaxPyramid;
use crate::lod::traversal::{traverse, BlockCaches, LodSelect};
use clap::Args;
use serde_json::json;
use std::path::{Path, PathBuf};

#[derive(Args, Debug)]
pub struct QualityArgs {
    #[command(flatten)]
    pub terrain: TerrainArgs,
    #[command(flatten)]
    pub frustum: FrustumArgs,
    #[command(flatten)]
    pub block: BlockArg,
    #[command(flatten)]
    pub morph: MorphArg,
    /// Camera path whose poses are measured.
    #[arg(long, value_enum, default_value_t = CameraPath::PaperFlyover)]
    pub path: CameraPath,
    /// Poses along the path (the first is the path's start view).
    #[arg(long, value_name = "N", default_value_t = 3, value_parser = parse_poses, allow_negative_numbers = true)]
    pub poses: u64,
    /// Output directory (quality.csv, quality.json, quality.png).
    #[arg(long, value_name = "DIR")]
    pub out: PathBuf,
}

/// One setting's result over all poses.
#[derive(Clone, Debug, serde::Serialize)]
pub struct Point {
    pub method: &'static str,
    /// delta (pixels) for strict and paper, the distance factor for distance LOD.
    pub parameter: f32,
    pub mean_triangles: f64,
    pub audited_max_px: f32,
    /// Blocks split only to keep a finer neighbour's stitched strip within delta (mean).
    pub mean_stitch_splits: f64,
}

/// Most poses a sweep takes: each is traversed 27 times (a million would run for days).
const MAX_POSES: u64 = 10_000;

fn parse_poses(s: &str) -> Result<u64, String> {
    match s.parse::<u64>() {
        Ok(n) if (1..=MAX_POSES).contains(&n) => Ok(n),
        _ => Err(format!("'{s}': a whole number from 1 to {MAX_POSES}")),
    }
}

const DELTAS: [f32; 9] = [0.35, 0.5, 0.7, 1.0, 1.4, 2.0, 2.8, 4.0, 5.6];
const FACTORS: [f32; 9] = [32.0, 22.6, 16.0, 11.3, 8.0, 5.66, 4.0, 2.83, 2.0];

pub fn quality(args: &QualityArgs) -> anyhow::Result<()> {
    crate::app::outputs::output_dir("--out", &args.out)?;
    let hf = args.terrain.load_heightfield(None)?;
    let layout = BlockLayout::of(&hf, args.block.k).map_err(InputError)?;
    let mm = MinMaxPyramid::build(&hf);
    let size = args.frustum.size.unwrap_or((640, 480));
    let cams: Vec<_> = (0..args.poses)
        .map(|i| path_camera(&hf, &mm, args.path, i, args.poses.max(2) * 2, args.frustum.fovy, size).0)
        .collect();
    let tpb = layout.triangles_per_block() as f64;
    let caches = BlockCaches::default();
    let mut points = Vec::new();
    let total = 2 * DELTAS.len() + FACTORS.len();
    let mut progress = crate::app::bench::Progress::counting("quality", total as u64, "settings");
    for (n, setting) in (0..total).enumerate() {
        let (method, parameter) = match setting {
            s if s < DELTAS.len() => ("strict", DELTAS[s]),
            s if s < 2 * DELTAS.len() => ("paper", DELTAS[s - DELTAS.len()]),
            s => ("distance", FACTORS[s - 2 * DELTAS.len()]),
        };
        let (mut tris, mut worst, mut splits) = (0.0f64, 0.0f32, 0.0f64);
        for cam in &cams {
            let t = match method {
                "distance" => traverse(&hf, &mm, &caches, &layout, cam, LodSelect::Distance { factor: parameter }),
                _ => {
                    let mode = if method == "strict" { ErrorMode::Strict } else { ErrorMode::Paper };
                    let errors = block_errors(&group_errors(&hf, &mm, &ErrorParams::new(cam, mode)), layout.m);
                    let select = LodSelect::errors(&errors, cam.position, parameter, mode).with_morph(args.morph.on());
                    traverse(&hf, &mm, &caches, &layout, cam, select)
                }
            };
            tris += t.blocks.len() as f64 * tpb;
            splits += t.stitch_splits as f64;
            worst = worst.max(audit(&hf, &layout, &t, cam).max_error_px);
        }
        let poses = cams.len() as f64;
        points.push(Point {
            method,
            parameter,
            mean_triangles: tris / poses,
            audited_max_px: worst,
            mean_stitch_splits: splits / poses,
        });
        progress.tick(n as u64 + 1);
    }

    let mut table = String::from("method,parameter,mean_triangles,audited_max_px,mean_stitch_splits\n");
    for p in &points {
        table += &format!(
            "{},{},{:.0},{:.4},{:.1}\n",
            p.method, p.parameter, p.mean_triangles, p.audited_max_px, p.mean_stitch_splits
        );
    }
    let csv = args.out.join("quality.csv");
    write_atomic(&csv, |tmp| std::fs::write(tmp, &table).map_err(|e| anyhow::anyhow!("{}: {e}", csv.display())))?;
    let strict: Vec<&Point> = points.iter().filter(|p| p.method == "strict").collect();
    let ratio = |other: &str| -> Vec<serde_json::Value> {
        let curve: Vec<&Point> = points.iter().filter(|p| p.method == other).collect();
        strict
            .iter()
            .filter_map(|s| {
                triangles_at(&curve, s.audited_max_px).map(|t| {
                    json!({"delta": s.parameter, "audited_max_px": s.audited_max_px, "ratio": s.mean_triangles / t})
                })
            })
            .collect()
    };
    let mut summary = json!({
        "heightmap": hf.source,
        "poses": args.poses,
        "size": [size.0, size.1],
        "block": layout.k(),
        "points": points,
        "strict_over_paper_at_equal_error": ratio("paper"),
        "strict_over_distance_at_equal_error": ratio("distance"),
    });
    crate::app::outputs::TerrainFacts::of(&hf).merge_into(&mut summary);
    let json_path = args.out.join("quality.json");
    let text = serde_json::to_string_pretty(&summary)?;
    write_atomic(&json_path, |tmp| {
        std::fs::write(tmp, &text).map_err(|e| anyhow::anyhow!("{}: {e}", json_path.display()))
    })?;
    let name = std::path::Path::new(&hf.source).file_name().map_or(hf.source.clone(), |n| n.to_string_lossy().into());
    plot(&args.out.join("quality.png"), &points, &name)?;
    crate::out!("{}", table.trim_end())?;
    crate::out!("{}", serde_json::to_string(&summary["strict_over_paper_at_equal_error"])?)?;
    crate::out!("{}", serde_json::to_string(&summary["strict_over_distance_at_equal_error"])?)?;
    Ok(())
}

/// Triangles `curve` needs for an audited maximum of `err`, interpolated linearly in
/// log-log between its settings; None outside the curve's range.
pub fn triangles_at(curve: &[&Point], err: f32) -> Option<f64> {
    let mut pts: Vec<(f64, f64)> = curve
        .iter()
        .filter(|p| p.audited_max_px > 0.0)
        .map(|p| ((p.audited_max_px as f64).ln(), p.mean_triangles.ln()))
        .collect();
    pts.sort_by(|a, b| a.0.total_cmp(&b.0));
    let e = (err as f64).ln();
    pts.windows(2).find(|w| w[0].0 <= e && e <= w[1].0).map(|w| {
        let f = if w[1].0 > w[0].0 { (e - w[0].0) / (w[1].0 - w[0].0) } else { 0.0 };
        (w[0].1 + (w[1].1 - w[0].1) * f).exp()
    })
}

fn plot(path: &Path, points: &[Point], title: &str) -> anyhow::Result<()> {
    use plotters::prelude::*;
    let have_font = plot_font();
    write_atomic(path, |tmp| {
        let root = BitMapBackend::new(tmp, (800, 560)).into_drawing_area();
        root.fill(&WHITE).map_err(|e| anyhow::anyhow!("plot: {e}"))?;
        let e_max = points.iter().map(|p| p.audited_max_px).fold(0.1f32, f32::max) as f64 * 1.2;
        let t_min = points.iter().map(|p| p.mean_triangles).fold(f64::INFINITY, f64::min).max(1.0) * 0.8;
        let t_max = points.iter().map(|p| p.mean_triangles).fold(1.0, f64::max) * 1.25;
        let mut chart = ChartBuilder::on(&root);
        chart.margin(14);
        if have_font {
            chart
                .caption(format!("{title}: triangles against audited max error"), ("sans-serif", 18))
                .x_label_area_size(36)
                .y_label_area_size(64);
        }
        let mut chart = chart
            .build_cartesian_2d((0.05f64..e_max).log_scale(), (t_min..t_max).log_scale())
            .map_err(|e| anyhow::anyhow!("plot: {e}"))?;
        let mut mesh = chart.configure_mesh();
        if have_font {
            mesh.x_desc("audited max screen-space error (px)")
                .y_desc("triangles (mean over poses)")
                .y_label_formatter(&|v| format!("{:.0}k", v / 1e3));
        }
        mesh.draw().map_err(|e| anyhow::anyhow!("plot: {e}"))?;
        for (method, color) in [("strict", RED), ("paper", BLUE), ("distance", BLACK)] {
            let mut data: Vec<(f64, f64)> = points
                .iter()
                .filter(|p| p.method == method && p.audited_max_px > 0.0)
                .map(|p| (p.audited_max_px as f64, p.mean_triangles))
                .collect();
            data.sort_by(|a, b| a.0.total_cmp(&b.0));
            let series = chart
                .draw_series(LineSeries::new(data.clone(), color.stroke_width(2)))
                .map_err(|e| anyhow::anyhow!("plot: {e}"))?;
            if have_font {
                series.label(method).legend(move |(x, y)| PathElement::new(vec![(x, y), (x + 20, y)], color));
            }
            chart
                .draw_series(data.into_iter().map(|p| Circle::new(p, 3, color.filled())))
                .map_err(|e| anyhow::anyhow!("plot: {e}"))?;
        }
        if have_font {
            chart
                .configure_series_labels()
                .background_style(WHITE.mix(0.8))
                .border_style(BLACK)
                .draw()
                .map_err(|e| anyhow::anyhow!("plot: {e}"))?;
        }
        root.present().map_err(|e| anyhow::anyhow!("plot: {e}"))?;
        Ok(())
    })
}
