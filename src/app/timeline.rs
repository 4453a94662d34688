//! `vkterrain timeline`: draws a trace (from `bench` or `view --trace`) as a picture, one
//! lane per thread and GPU queue, spans as bars, for documents and issues where a
//! Perfetto screenshot would not reproduce.

use crate::app::cli::InputError;
use crate::app::outputs::{plot_font, write_atomic};
use clap::Args;
use serde_json::Value;
use std::collections::BTreeMap;
use std::path::PathBuf;

#[derive(Args, Debug)]
pub struct TimelineArgs {
    /// A trace.json written by `bench` or `view --trace`.
    #[arg(long, value_name = "FILE.json")]
    pub trace: PathBuf,
    /// The picture to write.
    #[arg(long, value_name = "FILE.png")]
    pub out: PathBuf,
    /// Time window to draw, milliseconds from the trace's start: FROM,TO.
    #[arg(long, value_name = "FROM,TO", value_parser = parse_window, allow_hyphen_values = true)]
    pub window: Option<(f64, f64)>,
}

/// `--window FROM,TO`: finite milliseconds, FROM below TO (an infinite end would ask the
/// axis for endless ticks).
fn parse_window(w: &str) -> Result<(f64, f64), String> {
    let bad = || format!("'{w}': expected FROM,TO in milliseconds, finite numbers, FROM < TO");
    let (a, b) = w.split_once(',').ok_or_else(bad)?;
    let (a, b): (f64, f64) = (a.trim().parse().map_err(|_| bad())?, b.trim().parse().map_err(|_| bad())?);
    if !(a.is_finite() && b.is_finite() && a < b) {
        return Err(bad());
    }
    Ok((a, b))
}

/// A bar on a lane.
struct Span {
    lane: u32,
    name: String,
    start_ms: f64,
    end_ms: f64,
}

pub fn timeline(args: &TimelineArgs) -> anyhow::Result<()> {
    crate::input::regular_file(&args.trace).map_err(|e| InputError(format!("--trace {e}")))?;
    // Before the work: an output that cannot be written is a bad option (exit 2).
    crate::app::outputs::check_outputs(&[("--out", Some(&args.out))], &[("--trace", Some(&args.trace))])?;
    let text = std::fs::read_to_string(&args.trace)
        .map_err(|e| InputError(format!("--trace {}: {e}", args.trace.display())))?;
    let trace: Value = serde_json::from_str(&text)
        .map_err(|e| InputError(format!("--trace {}: not a trace: {e}", args.trace.display())))?;
    let events = trace["traceEvents"]
        .as_array()
        .ok_or_else(|| InputError(format!("--trace {}: no traceEvents", args.trace.display())))?;
    let mut lanes: BTreeMap<u32, String> = BTreeMap::new();
    let mut spans = Vec::new();
    for e in events {
        let tid = e["tid"].as_u64().unwrap_or(0) as u32;
        match e["ph"].as_str() {
            Some("M") if e["name"] == "thread_name" => {
                lanes.insert(tid, e["args"]["name"].as_str().unwrap_or("?").to_string());
            }
            Some("X") => {
                let (ts, dur) = (e["ts"].as_f64().unwrap_or(0.0), e["dur"].as_f64().unwrap_or(0.0));
                let name = e["name"].as_str().unwrap_or("").to_string();
                spans.push(Span { lane: tid, name, start_ms: ts / 1e3, end_ms: (ts + dur) / 1e3 });
            }
            _ => {}
        }
    }
    if spans.is_empty() {
        return Err(InputError(format!("--trace {}: no spans", args.trace.display())).into());
    }
    let (from, to) = args.window.unwrap_or((0.0, spans.iter().map(|s| s.end_ms).fold(0.0, f64::max)));
    let order: Vec<u32> = lanes.keys().copied().collect();
    draw(&args.out, &order, &lanes, &spans, (from, to))?;
    crate::out!("vkterrain: timeline {} ({} spans, {:.0}..{:.0} ms)", args.out.display(), spans.len(), from, to)?;
    Ok(())
}

/// The `i`-th distinct colour.
fn colour(i: usize) -> plotters::style::RGBColor {
    const PALETTE: [(u8, u8, u8); 8] = [
        (31, 119, 180),
        (255, 127, 14),
        (44, 160, 44),
        (214, 39, 40),
        (148, 103, 189),
        (140, 86, 75),
        (227, 119, 194),
        (127, 127, 127),
    ];
    let (r, g, b) = PALETTE[i % PALETTE.len()];
    plotters::style::RGBColor(r, g, b)
}

fn draw(
    path: &std::path::Path,
    order: &[u32],
    lanes: &BTreeMap<u32, String>,
    spans: &[Span],
    (from, to): (f64, f64),
) -> anyhow::Result<()> {
    use plotters::prelude::*;
    let have_font = plot_font();
    write_atomic(path, |tmp| {
        let height = 260 + 60 * order.len() as u32;
        let root = BitMapBackend::new(tmp, (1400, height)).into_drawing_area();
        root.fill(&WHITE).map_err(|e| anyhow::anyhow!("timeline: {e}"))?;
        // The legend goes in a strip right of the lanes.
        let (root, _) = root.split_horizontally(1400);
        let mut chart = ChartBuilder::on(&root);
        chart.margin(12);
        if have_font {
            chart.caption("vkterrain trace", ("sans-serif", 18)).x_label_area_size(30).y_label_area_size(280);
        }
        let n = order.len() as f64;
        let mut chart = chart.build_cartesian_2d(from..to, 0.0..n).map_err(|e| anyhow::anyhow!("timeline: {e}"))?;
        let names: Vec<String> = order.iter().map(|t| lanes[t].clone()).collect();
        let mut mesh = chart.configure_mesh();
        mesh.disable_y_mesh().y_labels(order.len() * 2 + 1);
        if have_font {
            let label = move |y: &f64| {
                let i = y.floor() as usize;
                if (y - y.floor() - 0.5).abs() < 0.01 && i < names.len() {
                    names[names.len() - 1 - i].clone()
                } else {
                    String::new()
                }
            };
            mesh.x_desc("time (ms)").y_label_formatter(&label);
            mesh.draw().map_err(|e| anyhow::anyhow!("timeline: {e}"))?;
        } else {
            mesh.disable_x_mesh().draw().map_err(|e| anyhow::anyhow!("timeline: {e}"))?;
        }
        // One colour per span name seen in the window, in name order (the legend's).
        let mut names: Vec<&str> =
            spans.iter().filter(|s| s.end_ms >= from && s.start_ms <= to).map(|s| s.name.as_str()).collect();
        names.sort_unstable();
        names.dedup();
        let index = |n: &str| names.iter().position(|m| *m == n).unwrap_or(0);
        // Long spans first, so that the phases inside a frame are drawn over it.
        let mut shown: Vec<&Span> = spans.iter().filter(|s| s.end_ms >= from && s.start_ms <= to).collect();
        shown.sort_by(|a, b| (b.end_ms - b.start_ms).total_cmp(&(a.end_ms - a.start_ms)));
        for s in shown {
            let Some(i) = order.iter().position(|&t| t == s.lane) else { continue };
            let row = (order.len() - 1 - i) as f64;
            let bar = Rectangle::new(
                [(s.start_ms.max(from), row + 0.15), (s.end_ms.min(to).max(s.start_ms.max(from)), row + 0.85)],
                colour(index(&s.name)).mix(0.8).filled(),
            );
            chart.draw_series(std::iter::once(bar)).map_err(|e| anyhow::anyhow!("timeline: {e}"))?;
        }
        if have_font {
            for (i, name) in names.iter().enumerate() {
                let c = colour(i);
                chart
                    .draw_series(std::iter::empty::<Rectangle<(f64, f64)>>())
                    .map_err(|e| anyhow::anyhow!("timeline: {e}"))?
                    .label(*name)
                    .legend(move |(x, y)| Rectangle::new([(x, y - 5), (x + 12, y + 5)], c.filled()));
            }
            chart
                .configure_series_labels()
                .position(SeriesLabelPosition::UpperRight)
                .background_style(WHITE.mix(0.9))
                .border_style(BLACK)
                .draw()
                .map_err(|e| anyhow::anyhow!("timeline: {e}"))?;
        }
        root.present().map_err(|e| anyhow::anyhow!("timeline: {e}"))?;
        Ok(())
    })
}
