//! The subcommands: `render` (one headless frame) and `errors` (one error generation).

use crate::app::cli::OnOff;
use crate::app::cli::{
    check_messages, option_error, BlockArg, CameraArgs, CommonArgs, Degraded, DeviceArgs, ErrorModeArg, InputError,
    StreamedOptions, TerrainArgs, TextureArgs,
};
use crate::app::outputs::{check_outputs, save_png, write_atomic};
use crate::draw::blocks::{BlocksRenderer, NormalSource, PixelPass, Shading, Target};
use crate::draw::frame::{traversal_threads, DrawThread, FrameRequest, LodChoice, LodTerrain};
use crate::draw::raycast::Raycast;
use crate::errors::activity::ErrorsActivity;
use crate::errors::feed::{ErrorFeed, RefreshPolicy};
use crate::gpu::terrain::TerrainGpu;
use crate::input::archive::Archive;
use crate::lod::audit;
use crate::lod::block::BlockLayout;
use crate::lod::gie::ErrorParams;
use crate::lod::heightfield::Heightfield;
use crate::lod::pyramid::MinMaxPyramid;
use crate::trace::Trace;
use crate::vk::{Device, DeviceOptions, Instance, InstanceOptions};
use clap::Args;
use serde_json::json;
use std::path::PathBuf;
use std::sync::Arc;
use std::time::{Duration, Instant};

#[derive(Args, Debug)]
pub struct RenderArgs {
    #[command(flatten)]
    pub common: CommonArgs,
    #[command(flatten)]
    pub textures: TextureArgs,
    /// LOD selection.
    #[arg(long, value_enum, default_value_t = LodChoice::Error)]
    pub lod: LodChoice,
    /// Output PNG.
    #[arg(long, value_name = "FILE.png")]
    pub out: PathBuf,
    /// Also write the drawn mesh (blocks, stitched edges, morph factors applied) as
    /// binary glTF, in world units (metres for georeferenced inputs).
    #[arg(long, value_name = "FILE.glb")]
    pub export_mesh: Option<PathBuf>,
    /// Also audit the block list: the largest screen-space error over every visible sample.
    #[arg(long)]
    pub audit: bool,
    /// Plain background instead of the sky (R,G,B in 0..1).
    #[arg(long, value_name = "R,G,B", allow_hyphen_values = true)]
    pub background: Option<String>,
    /// Tint blocks by LOD.
    #[arg(long)]
    pub colour_by_lod: bool,
    /// Exponential fog density per world unit (0 disables).
    #[arg(long, value_name = "DENSITY", default_value = "0", value_parser = crate::app::cli::non_negative, allow_negative_numbers = true)]
    pub fog: f32,
    /// Where normals come from: a gradient map made at load (default), or sixteen height
    /// fetches per pixel (the same image up to rounding, no map to make).
    #[arg(long, value_enum, default_value_t = NormalSource::GradientMap)]
    pub shading: NormalSource,
    /// How pixels are shaded: once each after a depth-only pass over the blocks
    /// (default), or as the blocks are drawn (forward: every covered fragment shaded).
    #[arg(long, value_enum, default_value_t = PixelPass::Deferred)]
    pub pixels: PixelPass,
    /// Blocks drawn by a fragment-shader ray-caster instead of as triangles:
    /// none, every other eligible block (the crack check), every eligible one (a block
    /// that neither morphs nor follows a coarser neighbour's edge), or those whose rays
    /// are estimated to cost less than their triangles (auto). Deferred frames only.
    #[arg(long, value_enum, default_value_t = Raycast::Off)]
    pub raycast: Raycast,
    #[command(flatten)]
    pub streamed: StreamedOptions,
}

#[derive(Args, Debug)]
pub struct ErrorsArgs {
    #[command(flatten)]
    pub terrain: TerrainArgs,
    #[command(flatten)]
    pub view: CameraArgs,
    #[command(flatten)]
    pub block: BlockArg,
    #[command(flatten)]
    pub device: DeviceArgs,
    #[command(flatten)]
    pub error_mode: ErrorModeArg,
    /// Generations to compute (the median update time is reported).
    #[arg(long, value_name = "N", default_value_t = 1, value_parser = crate::app::cli::at_least_one, allow_negative_numbers = true)]
    pub repeat: u64,
    /// Write the block-error pyramid as little-endian f32 (layout: docs/commands.md,
    /// "Block-error dump layout").
    #[arg(long, value_name = "FILE")]
    pub dump: Option<PathBuf>,
    #[command(flatten)]
    pub streamed: crate::app::cli::StreamedOptions,
}

/// `errors` on a terrain drawn from tiles: the errors activity's generations over the
/// atlas for the tiles the default (or given) view's selection reaches, `--repeat`
/// times, each for a camera moved a hundredth of a sample further (so that each is a new
/// generation), and their cost as JSON.
fn errors_over_tiles(args: &ErrorsArgs, device: Arc<Device>, archive: Arc<Archive>) -> anyhow::Result<()> {
    let (cache_mb, gpu_mb) = (args.streamed.cache_mb(&archive.meta), args.streamed.gpu_mb(&archive.meta));
    eprintln!("{}", crate::app::stream::streamed_banner(&args.terrain.name(), &archive.meta, cache_mb, gpu_mb));
    let r = crate::app::stream::errors_over_atlas(
        &archive,
        &device,
        (&args.terrain.frame, args.block.k),
        &args.view,
        (args.repeat, args.error_mode.mode),
        (cache_mb, gpu_mb),
        args.dump.as_deref(),
    )?;
    let mut out = r;
    out["validation"] = json!(device.instance.validation);
    out["validation_messages"] = json!(device.instance.validation.then(|| device.instance.validation_messages()));
    out["queue_mode"] = json!(device.queue_mode.as_str());
    out["device"] = json!(device.name);
    crate::app::outputs::TerrainFacts::of_archive(&archive.meta, &args.terrain.frame).merge_into(&mut out);
    crate::out!("{out}")?;
    if device.instance.validation && device.instance.validation_messages() > 0 {
        return Err(anyhow::anyhow!("{} validation messages", device.instance.validation_messages()));
    }
    Ok(())
}

/// Everything a command needs on the GPU.
pub struct Session {
    pub hf: Arc<Heightfield>,
    pub mm: MinMaxPyramid,
    pub layout: BlockLayout,
    pub device: Arc<Device>,
    pub terrain: Arc<TerrainGpu>,
    /// Time to build the group pyramid (min/max and exact deviation) on the CPU.
    pub pyramid_ms: f64,
}

impl Session {
    /// The terrain as the traversal reads it.
    pub fn lod_terrain(&self) -> LodTerrain<'_> {
        LodTerrain { hf: &self.hf, mm: &self.mm, layout: &self.layout }
    }

    /// Opens the device, loads the heightfield and `textures` (none for `errors`), and
    /// uploads them.
    pub fn open(
        terrain: &TerrainArgs,
        block: BlockArg,
        device: &DeviceArgs,
        textures: Option<&TextureArgs>,
    ) -> anyhow::Result<Self> {
        Session::with_device(open_device(device, block)?, terrain, block, textures)
    }

    /// [`Session::open`] on a device already open.
    pub fn with_device(
        device: Arc<Device>,
        terrain: &TerrainArgs,
        block: BlockArg,
        textures: Option<&TextureArgs>,
    ) -> anyhow::Result<Self> {
        let hf = terrain.load_heightfield(Some(device.max_image_dimension_2d() as usize))?;
        Session::check_size(&device, &hf)?;
        let layout = BlockLayout::of(&hf, block.k).map_err(InputError)?;
        if layout.k() != block.k {
            tracing::info!("block {} is larger than the terrain; using k = {}", block.k, layout.k());
        }
        let t = Instant::now();
        let mm = MinMaxPyramid::build(&hf);
        let pyramid_ms = t.elapsed().as_secs_f64() * 1e3;
        tracing::info!("group pyramid (min/max and exact deviation, {} levels) in {pyramid_ms:.0} ms", hf.n);
        let tex = textures.map(|t| t.load(&hf)).transpose()?.unwrap_or_default();
        if let Some(args) = textures {
            args.check_fits(tex.base.as_ref(), tex.detail.as_ref(), &device)?;
        }
        let terrain = Arc::new(TerrainGpu::new(&device, &hf, &mm, tex.base.as_ref(), tex.detail.as_ref())?);
        Ok(Session { hf: Arc::new(hf), mm, layout, device, terrain, pyramid_ms })
    }

    /// The viewport must fit in one image on this device.
    pub fn check_viewport(&self, size: (u32, u32)) -> Result<(), InputError> {
        crate::app::cli::check_image_size(&self.device, "--size", size)
    }

    /// The heightfield must fit in one image on this device.
    pub fn check_size(device: &Device, hf: &Heightfield) -> Result<(), InputError> {
        let max = device.max_image_dimension_2d() as usize;
        let [gw, gh] = hf.grid();
        if gw.max(gh) > max {
            return Err(InputError(format!(
                "{}: the {gw} x {gh} grid is larger than the device's maxImageDimension2D ({max})",
                hf.source
            )));
        }
        Ok(())
    }

    pub fn validation_messages(&self) -> u64 {
        self.device.instance.validation_messages()
    }
}

/// The headless device the options ask for, its queue mode and notes printed. The block
/// option is checked first, so that a bad value fails before anything starts.
pub fn open_device(args: &DeviceArgs, block: BlockArg) -> anyhow::Result<Arc<Device>> {
    BlockLayout::check(block.k).map_err(InputError)?;
    let instance = Instance::new(&InstanceOptions { validation: args.validation(), extensions: Vec::new() })?;
    let device = Device::new(instance, &DeviceOptions { gpu: args.gpu.clone(), queues: args.queues, swapchain: false })
        .map_err(option_error)?;
    eprintln!("vkterrain: device {}, queue mode {}", device.name, device.queue_mode.as_str());
    for note in device.notes() {
        eprintln!("vkterrain: note: {note}");
    }
    Ok(device)
}

/// The draw thread as the options set it up (its error feed's mode and refresh policy,
/// morphing, occlusion culling), recording into `trace`.
/// Its traversal runs on [`traversal_threads`] for `device`, when known (the viewer makes
/// its device later and sets them then).
pub fn draw_thread(common: &CommonArgs, trace: Trace, device: Option<&Device>) -> anyhow::Result<DrawThread> {
    let policy = RefreshPolicy { moved_fraction: common.refresh_at, max_share: common.update_share };
    let mut draw = DrawThread::new(ErrorFeed::new(common.error_mode.mode, policy), common.lod.morph.on(), trace)
        .with_occlusion(common.occlusion != Some(OnOff::Off));
    if let Some(device) = device {
        draw.set_threads(traversal_threads(common.lod.traversal_threads, device.properties.device_type))?;
    }
    Ok(draw)
}

fn parse_background(s: &str) -> Result<[f32; 3], InputError> {
    let v: Vec<f32> = s.split(',').filter_map(|p| p.trim().parse().ok()).collect();
    if v.len() != 3 || v.iter().any(|c| !(0.0..=1.0).contains(c)) {
        return Err(InputError(format!("--background '{s}': expected R,G,B with each in 0..1")));
    }
    Ok([v[0], v[1], v[2]])
}

pub fn render(args: &RenderArgs) -> anyhow::Result<()> {
    args.common.terrain.check_terrain()?;
    if !crate::app::outputs::is_png(&args.out) {
        return Err(InputError(format!("--out {}: the output must be a .png file", args.out.display())).into());
    }
    if let Some(p) = &args.export_mesh {
        if p.extension().and_then(|e| e.to_str()).map(|e| e.to_lowercase()) != Some("glb".into()) {
            return Err(InputError(format!(
                "--export-mesh {}: the mesh is written as binary glTF, a .glb file",
                p.display()
            ))
            .into());
        }
    }
    let [texture, detail] = args.textures.inputs();
    check_outputs(
        &[("--out", Some(&args.out)), ("--export-mesh", args.export_mesh.as_deref())],
        &[("--heightmap", args.common.terrain.heightmap.as_deref()), texture, detail],
    )?;
    let mut shading = Shading {
        fog_density: args.fog,
        colour_by_lod: args.colour_by_lod,
        normals: args.shading,
        pixels: args.pixels,
        raycast: args.raycast,
        ..Shading::default()
    };
    if let Some(bg) = &args.background {
        shading.sky = false;
        shading.background = parse_background(bg)?;
    }
    let shading = args.textures.shade(shading);
    let device = open_device(&args.common.device, args.common.block)?;
    // Before the terrain is opened (or cut into tiles): a size no image can have is
    // refused whatever is drawn.
    if let Some(size) = args.common.view.frustum.size {
        crate::app::cli::check_image_size(&device, "--size", size)?;
    }
    let max_side = || device.max_image_dimension_2d() as usize;
    if let Some((archive, stop)) =
        crate::app::stream::streamed_archive(&args.common.terrain, args.streamed.from_tiles(), max_side)?
    {
        return render_streamed(args, device, archive, stop.as_ref());
    }
    let s = Session::with_device(device, &args.common.terrain, args.common.block, Some(&args.textures))?;
    let cam = args.common.view.camera(&s.hf, (1280, 720))?;
    s.check_viewport((cam.width, cam.height))?;
    let mut renderer = BlocksRenderer::new(
        &s.device,
        &s.hf,
        &s.terrain,
        s.layout,
        crate::draw::blocks::COLOR_FORMAT,
        1,
        args.common.sun.0,
    )?;
    let target = Target::new(&s.device, cam.width, cam.height)?;

    let activity = if args.lod == LodChoice::Error {
        Some(ErrorsActivity::start(&s.device, s.terrain.clone(), s.hf.clone(), s.layout)?)
    } else {
        None
    };
    // `render` is the draw thread's first frame: it waits for the generation computed at
    // its own camera, so its output is deterministic.
    let mut draw = draw_thread(&args.common, Trace::off(), Some(&s.device))?;
    let request = FrameRequest { frame: 0, cam: &cam, lod: args.lod, delta: args.common.lod.delta, blocks: None };
    let frame = draw.step(activity.as_ref(), s.lod_terrain(), request, |blocks| {
        let t = Instant::now();
        let drawn = renderer.render_offscreen(&s.hf, &s.terrain, &target, &cam, blocks, &shading)?;
        Ok((drawn, t.elapsed().as_secs_f64() * 1e3))
    })?;
    let ((pixels, stats), frame_ms) = frame.submitted;
    let forward = args.pixels == crate::draw::blocks::PixelPass::Forward
        || args.colour_by_lod
        || args.common.terrain.voids == crate::input::load::VoidMode::Hole;
    note_if_nothing_was_cast(args, forward, stats.raycast_blocks, stats.draw_calls);
    let trav = frame.traversal.expect("render traverses");
    let generation = frame.taken.unwrap_or_default();
    let errors_ms = activity.is_some().then_some(frame.feed_ms);
    let traverse_ms = frame.traverse_ms;
    save_png(&args.out, cam.width, cam.height, &pixels)?;
    let exported = match &args.export_mesh {
        Some(path) => {
            let mesh = crate::lod::mesh::drawn_mesh(&s.hf, &s.layout, &trav.blocks);
            crate::app::export::write_glb(path, &mesh, &crate::app::outputs::TerrainFacts::of(&s.hf))?;
            Some(mesh)
        }
        None => None,
    };
    let audited = args.audit.then(|| audit::audit(&s.hf, &s.layout, &trav, &cam));
    if let Some(a) = activity {
        a.stop()?;
    }
    drop(renderer);
    drop(target);
    let mut out = json!({
        "width": cam.width,
        "height": cam.height,
        "lod": format!("{:?}", args.lod).to_lowercase(),
        "error_mode": args.common.error_mode.mode.as_str(),
        "delta": args.common.lod.delta,
        "triangles": stats.triangles,
        // Parts of drawn blocks left out (occluded or outside the frustum): the
        // exported mesh keeps them, so that it has no holes where the view had none.
        "hidden_parts": stats.hidden_parts,
        "hidden_triangles": stats.hidden_parts * s.layout.triangles_per_part(),
        "draw_calls": stats.draw_calls,
        "raycast": crate::app::cli::value_name(args.raycast),
        "raycast_blocks": stats.raycast_blocks,
        "blocks": trav.blocks.len(),
        "occlusion": trav.occlusion,
        "error_generation": generation,
        "max_block_error_px": trav.max_block_error,
        "stitch_splits": trav.stitch_splits,
        "traverse_ms": traverse_ms,
        "frame_ms": frame_ms,
        "geometry_bytes": renderer_geometry_bytes(s.layout.k()),
        "heightfield_bytes": s.hf.gpu_bytes(),
        "grid": s.hf.grid(),
        "roots": s.hf.roots,
        "queue_mode": s.device.queue_mode.as_str(),
        "device": s.device.name,
        "camera": [cam.position.x, cam.position.y, cam.position.z],
        "validation_messages": s.validation_messages(),
    });
    crate::app::outputs::TerrainFacts::of(&s.hf).merge_into(&mut out);
    if let Some(m) = &exported {
        mesh_into(&mut out, m);
    }
    if let Some(ms) = errors_ms {
        out["error_update_ms"] = json!(ms);
    }
    if let Some(a) = audited {
        audit_into(&mut out, &a, args.common.lod.delta);
    }
    crate::out!("{out}")?;
    finish(s)
}

/// An exported mesh's figures in a render's JSON.
fn mesh_into(out: &mut serde_json::Value, m: &crate::lod::mesh::DrawnMesh) {
    out["mesh_vertices"] = json!(m.positions.len());
    out["mesh_triangles"] = json!(m.triangles());
    out["mesh_triangles_beyond_extent"] = json!(m.beyond_extent);
    out["mesh_triangles_in_holes"] = json!(m.in_holes);
}

/// The audit's figures in a render's JSON. JSON has no infinity: a drawn point behind the
/// eye (an unbounded error) is reported as `audit_unbounded` with null figures.
fn audit_into(out: &mut serde_json::Value, a: &audit::AuditResult, delta: f32) {
    out["max_audited_error_px"] = json!(a.max_error_px);
    out["audited_over_delta"] = json!(a.max_error_px / delta);
    out["audit_unbounded"] = json!(!a.max_error_px.is_finite());
    out["audit_within_delta"] = json!(a.max_error_px <= delta * 1.01);
    out["audited_samples"] = json!(a.samples);
    out["uncovered_samples"] = json!(a.uncovered);
}

/// Says why, when `--raycast` was asked for and a frame of `draw_calls` ray-cast no block
/// (`forward`: the frame was shaded forward).
fn note_if_nothing_was_cast(args: &RenderArgs, forward: bool, raycast_blocks: u64, draw_calls: u64) {
    if args.raycast == Raycast::Off || raycast_blocks > 0 || draw_calls == 0 {
        return;
    }
    let why = if forward {
        "blocks are ray-cast in frames shaded deferred only, and this one was shaded forward (--pixels \
         forward, --colour-by-lod and --voids hole shade forward, and from tiles --shading heights)"
    } else {
        "a block is cast only when it is not morphing, meets no coarser neighbour and lies inside the \
         terrain's extent, in a frame shaded deferred (a camera too far for the depth pass shades forward); \
         --morph off leaves more blocks to cast"
    };
    eprintln!(
        "vkterrain: note: --raycast {}: no block of this view was ray-cast: {why}",
        crate::app::cli::value_name(args.raycast)
    );
}

/// `render` over an archive drawn streamed ([`crate::app::stream::render_archive`]).
/// `stop`: the signal handlers a preparation on the fly left (obeyed between steps).
fn render_streamed(
    args: &RenderArgs,
    device: Arc<Device>,
    archive: Arc<Archive>,
    stop: Option<&crate::app::signals::Stop>,
) -> anyhow::Result<()> {
    let shown = args.common.terrain.name();
    let m = &archive.meta;
    let gpu_mb = args.streamed.gpu_mb(m);
    eprintln!("{}", crate::app::stream::streamed_banner(&shown, m, args.streamed.cache_mb(m), gpu_mb));
    let queue_mode = device.queue_mode.as_str();
    let messages = device.instance.messages.clone();
    let r = crate::app::stream::render_archive(crate::app::stream::ArchiveFrame {
        archive: archive.clone(),
        device,
        common: &args.common,
        delta: args.common.lod.delta,
        fog: args.fog,
        cache_mb: args.streamed.cache_mb(m),
        gpu_mb,
        colour_by_lod: args.colour_by_lod,
        background: args.background.as_deref().map(parse_background).transpose()?,
        export_mesh: args.export_mesh.is_some(),
        stop,
        lod: args.lod,
        normals: args.shading,
        pixels: args.pixels,
        textures: &args.textures,
        raycast: args.raycast,
    })?;
    let mut out = r.report;
    let count = |key: &str| out[key].as_u64().unwrap_or(0);
    let forward = out["pixels"] == "forward";
    note_if_nothing_was_cast(args, forward, count("raycast_blocks"), count("draw_calls"));
    if args.audit {
        // Offline, against every sample (SPEC 8): the whole terrain in memory, which the
        // streamed path itself never holds.
        let hf = args
            .common
            .terrain
            .load_heightfield(None)
            .map_err(|e| InputError(format!("--audit compares the frame with every sample, in memory: {e:#}")))?;
        let cam = r.view.absolute();
        // In the archive's block layout (one square of 2^n + 1 samples a side), which is
        // not the in-memory one for every size: the samples beyond the true extent repeat
        // its edge in both.
        audit_into(&mut out, &audit::audit_blocks(&hf, &r.layout, &r.drawn, &cam), args.common.lod.delta);
    }
    // Outputs last, so that a stop asked for before leaves none.
    crate::app::stream::exit_if_stopped(stop);
    save_png(&args.out, r.width, r.height, &r.pixels)?;
    if let (Some(path), Some(m)) = (&args.export_mesh, &r.mesh) {
        let facts = crate::app::outputs::TerrainFacts::of_archive(&archive.meta, &args.common.terrain.frame);
        crate::app::export::write_glb(path, m, &facts)?;
        mesh_into(&mut out, m);
    }
    out["queue_mode"] = json!(queue_mode);
    out["error_mode"] = json!(args.common.error_mode.mode.as_str());
    crate::app::outputs::TerrainFacts::of_archive(&archive.meta, &args.common.terrain.frame).merge_into(&mut out);
    let failure = out["first_failure"].as_str().map(str::to_string);
    out["degraded"] = json!(failure.is_some());
    crate::out!("{out}")?;
    // Every Vulkan object is gone now: messages from their destruction count too.
    check_messages(&messages)?;
    if let Some(failure) = failure {
        return Err(Degraded(format!(
            "tiles could not be read (first: {failure}); the frame was drawn without their data (worst {:.2}x delta)",
            out["worst_factor"]
        ))
        .into());
    }
    if !out["within_bound"].as_bool().unwrap_or(false) {
        let why = format!(
            "the budgets (--cache-mb {}, --gpu-mb {}) cannot hold the tiles this view needs",
            args.streamed.cache_mb(&archive.meta),
            gpu_mb
        );
        eprintln!(
            "vkterrain: WARNING: the frame is over the bound ({} blocks, worst {:.2}x delta): {why}",
            out["blocks_over_bound"], out["worst_factor"]
        );
    }
    Ok(())
}

/// Bytes of the shared block mesh (vertex + index buffer).
pub fn renderer_geometry_bytes(k: u32) -> u64 {
    let (v, i) = crate::lod::block::block_mesh_data(k);
    let index_size = if k * k <= 65536 { 2 } else { 4 };
    (v.len() + i.len() * index_size) as u64
}

/// Destroys the session, then fails when validation reported anything, including the
/// object tracker's leak reports at vkDestroyDevice / vkDestroyInstance.
fn finish(s: Session) -> anyhow::Result<()> {
    let messages = s.device.instance.messages.clone();
    drop(s);
    check_messages(&messages)
}

pub fn errors(args: &ErrorsArgs) -> anyhow::Result<()> {
    // Checked before the device and the generations: a dump that cannot be written
    // would otherwise fail at the end.
    args.terrain.check_terrain()?;
    check_outputs(&[("--dump", args.dump.as_deref())], &[("--heightmap", args.terrain.heightmap.as_deref())])?;
    let device = open_device(&args.device, args.block)?;
    let max_side = || device.max_image_dimension_2d() as usize;
    if let Some((archive, _)) =
        crate::app::stream::streamed_archive(&args.terrain, args.streamed.from_tiles(), max_side)?
    {
        return errors_over_tiles(args, device, archive);
    }
    let s = Session::with_device(device, &args.terrain, args.block, None)?;
    let cam = args.view.camera(&s.hf, (1280, 720))?;
    let activity = ErrorsActivity::start(&s.device, s.terrain.clone(), s.hf.clone(), s.layout)?;
    let base = ErrorParams::new(&cam, args.error_mode.mode);
    let mut times = Vec::new();
    let mut gpu_times = Vec::new();
    let mut last = None;
    for i in 0..args.repeat {
        // Each repeat moves the camera by a hundredth of the sample spacing (well above f32
        // resolution at terrain coordinates) so that a new generation is needed.
        let mut p = base;
        p.camera.x += i as f32 * s.hf.spacing.x * 0.01;
        let t = Instant::now();
        let g = activity.wait_for(p, Duration::from_secs(600))?;
        times.push(t.elapsed().as_secs_f64() * 1e3);
        gpu_times.extend(g.gpu_ms);
        if i == 0 {
            last = Some(g);
        }
    }
    let cost = activity.cost;
    activity.stop()?;
    times.sort_by(|a, b| a.partial_cmp(b).unwrap());
    gpu_times.sort_by(|a, b| a.partial_cmp(b).unwrap());
    let g = last.expect("at least one generation");
    if let Some(path) = &args.dump {
        let bytes: Vec<u8> = g.errors.packed().iter().flat_map(|v| v.to_le_bytes()).collect();
        write_atomic(path, |tmp| std::fs::write(tmp, &bytes).map_err(|e| anyhow::anyhow!("{}: {e}", path.display())))?;
    }
    let n = s.hf.n as u64;
    let mut out = json!({
        "n": n,
        "grid": s.hf.grid(),
        "roots": s.hf.roots,
        "levels": cost.levels,
        "block": s.layout.k(),
        "block_levels": s.layout.root_lod(),
        "error_mode": args.error_mode.mode.as_str(),
        "fragments_shaded": cost.fragments_shaded,
        "naive_fragments_n_4n": n * ((s.hf.grid()[0] - 1) * (s.hf.grid()[1] - 1)) as u64,
        "readback_bytes": cost.readback_bytes,
        "pyramid_ms": s.pyramid_ms,
        "geometry_bytes": renderer_geometry_bytes(s.layout.k()),
        "full_error_texture_bytes": (s.hf.grid()[0] * s.hf.grid()[1] * 4) as u64,
        "update_ms": times[times.len() / 2],
        "update_ms_min": times[0],
        "update_gpu_ms": gpu_times.get(gpu_times.len() / 2),
        "validation": s.device.instance.validation,
        "repeat": args.repeat,
        "root_error_px": g.errors.root_error(),
        "queue_mode": s.device.queue_mode.as_str(),
        "device": s.device.name,
        "validation_messages": s.validation_messages(),
    });
    crate::app::outputs::TerrainFacts::of(&s.hf).merge_into(&mut out);
    crate::out!("{out}")?;
    finish(s)
}
