//! Inputs for comparing an archive drawn streamed with a build older than archives
//! (docs/benchmarks.md, "Against build 2c8578c"): the archive's level-0 heights as a raw
//! little-endian `.r16` file, and the paper flyover's poses over the terrain loaded in
//! memory as a pose file (`bench --path`), so that both builds fly the same cameras.
//!
//! `cargo run --example reference_inputs -- ARCHIVE OUT.r16 OUT-poses.txt [FRAMES]`

use vkterrain::app::paths::{path_camera_over, CameraPath, PathTerrain};
use vkterrain::input::load::{load, LoadOptions};
use vkterrain::lod::pyramid::MinMaxPyramid;

fn main() -> anyhow::Result<()> {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let [archive, raw, poses, rest @ ..] = args.as_slice() else {
        anyhow::bail!("usage: reference_inputs ARCHIVE OUT.r16 OUT-poses.txt [FRAMES]");
    };
    let frames: u64 = rest.first().map_or(Ok(60), |f| f.parse())?;
    let hf = load(std::path::Path::new(archive), &LoadOptions::default())?;
    let g = hf.grid()[0];
    let mut out = Vec::with_capacity(hf.width * hf.height * 2);
    for z in 0..hf.height {
        for x in 0..hf.width {
            let v = hf.raw[z * g + x];
            anyhow::ensure!(v.fract() == 0.0 && (0.0..=65535.0).contains(&v), "{archive}: height {v} is not 16-bit");
            out.extend_from_slice(&(v as u16).to_le_bytes());
        }
    }
    std::fs::write(raw, out)?;
    let terrain = PathTerrain::of(&hf, &MinMaxPyramid::build(&hf));
    let mut text = String::new();
    for i in 0..frames {
        let (c, _) = path_camera_over(&terrain, CameraPath::PaperFlyover, i, frames, 60.0, (640, 480));
        let l = c.position + c.forward;
        text += &format!("{} {} {} {} {} {}\n", c.position.x, c.position.y, c.position.z, l.x, l.y, l.z);
    }
    std::fs::write(poses, text)?;
    eprintln!(
        "{archive}: {} x {} samples (spacing {:?}, {} m a unit) -> {raw}, {frames} poses -> {poses}",
        hf.width, hf.height, hf.spacing, hf.height_scale
    );
    Ok(())
}
