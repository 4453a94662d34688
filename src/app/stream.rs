//! `vkterrain stream`: a headless low flight over a tile archive (IO thread, host cache,
//! the traversal over resident tiles), frame by frame at a fixed rate, with what it read,
//! held and drew as JSON. With `--gpu-mb` every frame is also drawn on the GPU from the
//! heightfield atlas ([`crate::draw::streamed`]); without it, frames are selections.

use crate::app::cli::{CommonArgs, Degraded, InputError, Interrupted, OnOff, TerrainArgs};
use crate::app::signals::Stop;
use crate::draw::frame::{traversal_threads, LodChoice};
use crate::draw::lighting::Sun;
use crate::draw::lighting_gpu::OwnLighting;
use crate::draw::streamed::{FrameView, HeightRange, Overlay, StreamedRenderer, WindowImage};
use crate::errors::atlas::HeightAtlas;
use crate::input::archive::bytes::is_url;
use crate::input::archive::{Archive, Meta};
use crate::input::georef;
use crate::lod::morph::MorphRule;
use crate::lod::traversal::DISTANCE_FACTOR;
use crate::lod::view::{near_plane_for, view_of_box};
use crate::stream::io::TileSource;
use crate::stream::streamer::{StreamStats, Streamer};
use crate::stream::traverse::{Selection, StreamedLod, View};
use crate::stream::{Grid, TileKey};
use crate::trace::{Trace, DRAW_TID, IO_TID};
use crate::vk::Device;
use glam::DVec3;
use std::path::PathBuf;
use std::sync::Arc;
use std::time::{Duration, Instant};

#[derive(clap::Args, Debug)]
pub struct StreamArgs {
    /// The terrain to fly over (an archive is read tile by tile; a file, or the built-in
    /// terrain, is cut into tiles in memory first).
    #[command(flatten)]
    pub terrain: TerrainArgs,
    /// Host cache budget for decoded tiles, MB (as the other commands').
    #[arg(long, value_name = "MB", default_value_t = 256, value_parser = clap::value_parser!(u32).range(1..=1_000_000), allow_negative_numbers = true)]
    pub cache_mb: u32,
    /// Frames to fly.
    #[arg(long, value_name = "N", default_value_t = 1800, value_parser = crate::app::cli::at_least_one, allow_negative_numbers = true)]
    pub frames: u64,
    /// Frame rate the flight is paced at (the IO thread has 1/FPS s a frame).
    #[arg(long, default_value_t = 30.0, value_parser = parse_fps, allow_negative_numbers = true)]
    pub fps: f32,
    /// Height above the ground, world units.
    #[arg(long, default_value_t = 200.0, value_parser = crate::app::cli::positive, allow_negative_numbers = true)]
    pub altitude: f32,
    /// Ground speed, world units a second (a low-flying jet: 300 m/s).
    #[arg(long, default_value_t = 300.0, value_parser = crate::app::cli::positive, allow_negative_numbers = true)]
    pub speed: f32,
    /// Viewport size in pixels.
    #[arg(long, value_name = "WxH", default_value = "640x480", value_parser = crate::app::cli::parse_size, allow_hyphen_values = true)]
    pub size: (u32, u32),
    /// Drop the archive from the page cache first (posix_fadvise DONTNEED), so that the
    /// flight reads from the disk.
    #[arg(long)]
    pub cold: bool,
    /// Draw every frame on the GPU, from a heightfield atlas of this many MB (one layer a
    /// tile, at most 2048 layers). Without it the flight is the host side only.
    #[arg(long, value_name = "MB", value_parser = clap::value_parser!(u32).range(1..=1_000_000), allow_negative_numbers = true)]
    pub gpu_mb: Option<u32>,
    /// With --gpu-mb: write the last frame drawn here.
    #[arg(long, value_name = "FILE.png", requires = "gpu_mb")]
    pub out: Option<PathBuf>,
    /// With --gpu-mb: the device that draws the frames, and its validation.
    #[command(flatten)]
    pub device: crate::app::cli::DeviceArgs,
    /// The threshold, the morph (paid for inside the bound from the tiles' summaries)
    /// and the traversal's threads (1 without `--gpu-mb`).
    #[command(flatten)]
    pub lod: crate::app::cli::LodArgs,
    #[command(flatten)]
    pub block: crate::app::cli::BlockArg,
    /// With --gpu-mb for the paper's mode: its errors are shaded on the GPU.
    #[command(flatten)]
    pub error_mode: crate::app::cli::ErrorModeArg,
}

/// How a streamer's drawn blocks morph for `--morph`.
pub(crate) fn morph_rule(morph: OnOff) -> Option<MorphRule> {
    (morph == OnOff::On).then_some(MorphRule::Bounded)
}

/// What a viewer or `render` says when it opens `shown` streamed: a note, as the notes
/// on a file's georeferencing (an error line is the only other kind).
pub(crate) fn streamed_banner(shown: &str, m: &Meta, cache_mb: u32, gpu_mb: u32) -> String {
    format!(
        "vkterrain: note: {shown}: {} x {} samples, {} tile levels, drawn from its tiles (cache {cache_mb} MB, atlas {gpu_mb} MB)",
        m.width,
        m.height,
        m.top_level + 1,
    )
}

/// The GPU side of streamed frames: device, atlas and renderer, and what they did.
pub(crate) struct GpuFrames {
    /// Before the atlas: its frames are waited for before the atlas's thread stops.
    renderer: StreamedRenderer,
    /// Sun shadows and ambient occlusion (after the renderer, whose frames read it).
    lighting: OwnLighting,
    /// Why the frames have no shadows, when the lighting map's heights could not be read.
    no_shadows: Option<String>,
    atlas: HeightAtlas,
    pub device: Arc<Device>,
    /// The terrain's heights (the colour ramp, sea level).
    pub range: HeightRange,
    /// Exponential fog density per world unit.
    pub fog: f32,
    /// Unit vector towards the sun ([`GpuFrames::sun`]), and the sun asked for.
    light: glam::Vec3,
    sun: Option<Sun>,
    /// Blocks tinted by their LOD.
    pub colour_by_lod: bool,
    /// Edges only (the viewer's F).
    pub wireframe: bool,
    /// A plain background instead of the sky.
    pub background: Option<[f32; 3]>,
    /// Occlusion culling (`--occlusion`, the viewer's C key): hidden blocks and parts are
    /// not drawn; when the sweep runs ([`crate::lod::occlusion::Probe`]), what the last
    /// frame's did, each block's hidden parts (in the selection's order; empty when not
    /// culled), and the blocks hidden whole over every frame.
    pub occlusion: bool,
    probe: crate::lod::occlusion::Probe,
    pub last_occlusion: Option<crate::lod::block::OcclusionReport>,
    pub culled_masks: Vec<u16>,
    occluded_blocks: u64,
    frames: u64,
    /// Frames where some block's tile found no atlas layer (those blocks not drawn).
    pub frames_missing_blocks: u64,
    /// What the last frame drew: blocks, triangles, parts left out (outside the
    /// frustum), draws, ray-cast blocks, its GPU time (timestamps, when the device has
    /// them), whether it was shaded deferred.
    pub drawn: crate::draw::streamed::StreamedStats,
    /// Frames shaded deferred.
    pub deferred_frames: u64,
    /// Blocks drawn by rays (`--raycast`; [`crate::stream::draw::choose_raycast`]).
    pub raycast: crate::draw::raycast::Raycast,
    /// Parts left out over every frame drawn.
    hidden_parts_total: u64,
    drawing: Duration,
    /// The last frame drawn offscreen (RGBA8, sRGB), when `read_back`.
    pub last: Vec<u8>,
    /// Offscreen frames are read back into `last` (a benchmark's are not).
    pub read_back: bool,
    trace: Trace,
}

impl GpuFrames {
    /// An atlas of `mb` MB on `device`, attached to `streamer` (tiles it reads are
    /// uploaded by the atlas's thread before the traversal may use them), and a `size`
    /// target; `range`: the terrain's heights (the colour ramp). Frames and the atlas's
    /// uploads are recorded in `trace`.
    pub fn new(
        device: Arc<Device>,
        streamer: &mut Streamer,
        mb: u32,
        range: HeightRange,
        size: (u32, u32),
        trace: &Trace,
    ) -> anyhow::Result<Self> {
        let grid = &streamer.grid.clone();
        let atlas = HeightAtlas::traced(&device, grid, u64::from(mb) << 20, trace.clone())
            .map_err(|e| InputError(e.to_string()))?;
        eprintln!(
            "vkterrain: atlas of {} layers ({} x {} {}) on {}, uploaded by its own thread on the {} queue",
            atlas.layer_count(),
            atlas.side(),
            atlas.side(),
            if atlas.unorm16() { "16-bit" } else { "float" },
            device.name,
            if device.queue_mode == crate::vk::QueueMode::Shared { "shared" } else { "errors" },
        );
        streamer.attach(Box::new(atlas.feed()), HeightAtlas::cache_tiles(atlas.layer_count()));
        let mut renderer = StreamedRenderer::new(&device, crate::stream::draw::layout(grid), size.0, size.1)?;
        renderer.set_holes(grid.holes);
        let t0 = Instant::now();
        let (lighting, no_shadows) = match crate::draw::streamed::lighting_heights(
            streamer.source().as_ref(),
            grid,
            "the archive",
            streamer.stop.as_deref(),
        ) {
            Ok(Some((hf, stride))) => {
                let sea = crate::lod::heightfield::sea_level(range.absolute, range.world);
                (OwnLighting::new(&device, hf, stride, [grid.width, grid.height], None, sea)?, None)
            }
            Ok(None) => {
                let why = format!(
                    "a {} x {} terrain is too long and narrow for one lighting map: frames without shadows",
                    grid.width, grid.height
                );
                eprintln!("vkterrain: note: {why}");
                (OwnLighting::everything_lit(&device)?, Some(why))
            }
            // Stopped: the run ends before any frame needs the map.
            Err(_) if streamer.stopped() => (OwnLighting::everything_lit(&device)?, Some("stopped".into())),
            Err(e) => {
                tracing::warn!("streamed frames without shadows: {e:#}");
                // Frames drawn without their data: the run finishes degraded.
                if streamer.first_failure.is_none() {
                    streamer.first_failure = Some(format!("the lighting map's heights: {e:#}"));
                }
                (OwnLighting::everything_lit(&device)?, Some(format!("{e:#}")))
            }
        };
        if no_shadows.is_none() {
            eprintln!(
                "vkterrain: lighting map {} x {} (shadows, ambient occlusion) from samples {} apart (heights read and uploaded in {:.0} ms)",
                lighting.map.image.extent.width,
                lighting.map.image.extent.height,
                lighting.source().stride,
                t0.elapsed().as_secs_f64() * 1e3
            );
        }
        Ok(GpuFrames {
            atlas,
            renderer,
            lighting,
            no_shadows,
            device,
            range,
            fog: 0.0,
            light: Sun::DEFAULT.direction(),
            sun: None,
            colour_by_lod: false,
            wireframe: false,
            background: None,
            occlusion: true,
            probe: Default::default(),
            last_occlusion: None,
            culled_masks: Vec::new(),
            occluded_blocks: 0,
            frames: 0,
            frames_missing_blocks: 0,
            drawn: Default::default(),
            deferred_frames: 0,
            raycast: crate::draw::raycast::Raycast::Off,
            hidden_parts_total: 0,
            drawing: Duration::ZERO,
            last: Vec::new(),
            read_back: true,
            trace: trace.clone(),
        })
    }

    /// Where the frames' normals come from (`--shading`), set before the first frame.
    pub fn set_normals(&mut self, normals: crate::draw::blocks::NormalSource) {
        self.renderer.set_normals(normals);
    }

    /// Deferred (the default) or forward shading (`--pixels`).
    pub fn set_pixels(&mut self, pixels: crate::draw::blocks::PixelPass) {
        self.renderer.set_pixels(pixels);
    }

    /// The textures `args` named, read over the terrain (`TextureArgs::load_over`), set
    /// before the first frame: the detail weighted as `args` says.
    pub fn set_textures(
        &mut self,
        t: &crate::app::cli::Textures,
        args: &crate::app::cli::TextureArgs,
    ) -> anyhow::Result<()> {
        if t.base.is_none() && t.detail.is_none() {
            return Ok(());
        }
        args.check_fits(t.base.as_ref(), t.detail.as_ref(), &self.device)?;
        let weight = if t.detail.is_some() { args.detail_weight } else { 1.0 };
        self.renderer.set_textures(t.base.as_ref(), t.detail.as_ref(), args.detail_tiling, weight)?;
        Ok(())
    }

    /// Draws the frame (every tile the selection used is in the atlas: the cache takes
    /// only tiles the atlas's thread has uploaded): offscreen (kept in `last`), or into a
    /// window's swapchain image with its overlay (the panel) drawn over the terrain.
    pub fn draw(
        &mut self,
        streamer: &Streamer,
        grid: &Grid,
        view: &View,
        sel: &Selection,
        window: Option<(&WindowImage, Option<Overlay>)>,
    ) -> anyhow::Result<()> {
        let t0 = Instant::now();
        let mut blocks = crate::stream::draw::stitched_blocks(grid, &streamer.cache, sel);
        if let Some(failure) = self.atlas.failure() {
            anyhow::bail!(failure);
        }
        let (anchor, cam) = view.relative(grid);
        self.culled_masks.clear();
        self.last_occlusion = None;
        if self.occlusion {
            let (atlas, cache, masks) = (&self.atlas, &streamer.cache, &mut self.culled_masks);
            let tpp = crate::stream::draw::layout(grid).triangles_per_part();
            let report = self.probe.run(blocks.len(), tpp, || {
                let drawable = |t| atlas.holds(t);
                let culled = &sel.frustum_culled;
                let rule = (crate::lod::occlusion::Rule::Sound, masks);
                crate::stream::draw::cull(grid, cache, (anchor, &cam), (&mut blocks, culled), &drawable, rule)
            });
            self.occluded_blocks += report.hidden as u64;
            self.last_occlusion = Some(report);
        }
        crate::stream::draw::hide_parts_outside(grid, &streamer.cache, anchor, &cam, &mut blocks);
        let mut raycast_pixels = 0.0;
        if self.raycast != crate::draw::raycast::Raycast::Off {
            let under = sees_the_underside(grid, streamer, view.position, self.range.world[1]);
            let ring = self.renderer.ring_triangles();
            let choice = (self.raycast, ring, under);
            raycast_pixels = choose_raycast(grid, &streamer.cache, (anchor, &cam), &mut blocks, choice);
        }
        let fv = FrameView {
            grid,
            anchor,
            cam,
            heights: self.range,
            fog: self.fog,
            light: self.light,
            lighting: &self.lighting,
            colour_by_lod: self.colour_by_lod,
            wireframe: self.wireframe,
            background: self.background,
        };
        let stats = match window {
            Some((w, overlay)) => self.renderer.render_to_window(&self.atlas, &fv, &blocks, w, overlay)?,
            None if !self.read_back => self.renderer.render_unread(&self.atlas, &fv, &blocks)?,
            None => {
                let (pixels, stats) = self.renderer.render(&self.atlas, &fv, &blocks)?;
                self.last = pixels;
                stats
            }
        };
        self.frames_missing_blocks += (stats.missing > 0) as u64;
        self.frames += 1;
        self.drawn = crate::draw::streamed::StreamedStats { raycast_pixels, ..stats };
        // What a triangle costs the GPU now: whether the next sweep pays is judged by it.
        self.probe.observe(stats.gpu_ms, stats.triangles);
        self.deferred_frames += u64::from(stats.deferred);
        self.hidden_parts_total += stats.hidden_parts;
        self.drawing += t0.elapsed();
        let args = serde_json::json!({
            "frame": self.frames,
            "blocks": stats.blocks,
            "missing": stats.missing,
            "hidden_parts": stats.hidden_parts,
        });
        self.trace.complete(DRAW_TID, "draw (record, submit, wait)", t0, Instant::now(), args);
        Ok(())
    }

    /// Occlusion culling starts afresh, as a new run's frames do (the sweep runs on the
    /// next frame whatever the last run's paid).
    pub fn new_run(&mut self) {
        self.probe = Default::default();
    }

    /// Lights the frames from `sun`'s direction with its shadows and ambient occlusion
    /// (`--sun`; with none, from the default direction without them, as in memory).
    pub fn sun(&mut self, sun: Option<Sun>) -> anyhow::Result<()> {
        self.light = sun.unwrap_or(Sun::DEFAULT).direction();
        self.sun = sun;
        if self.no_shadows.is_none() {
            self.lighting.set_sun(sun)?;
            if sun.is_some() {
                eprintln!("vkterrain: lighting map drawn for the sun in {:.0} ms", self.lighting.map.last_ms());
            }
        }
        Ok(())
    }

    /// The sun the frames are lit by ([`GpuFrames::sun`]), and how long its lighting map
    /// took (ms).
    pub fn lit_sun(&self) -> (Option<Sun>, f64) {
        (self.sun, self.lighting.map.last_ms())
    }

    /// Whether deferred shading is asked for (a frame may still shade forward:
    /// [`GpuFrames::deferred`] says what the last one did).
    pub fn deferred_asked(&self) -> bool {
        self.renderer.pixels() == crate::draw::blocks::PixelPass::Deferred
    }

    /// Redraws the lighting map for heights at `scale` world units per raw unit (the
    /// viewer's vertical exaggeration).
    pub fn set_height_scale(&mut self, scale: f64) -> anyhow::Result<()> {
        if self.no_shadows.is_none() {
            self.lighting.set_height_scale(scale as f32)?;
        }
        Ok(())
    }

    /// Offscreen frames at `width x height` from now on (a window's screenshot).
    pub fn resize(&mut self, width: u32, height: u32) -> anyhow::Result<()> {
        self.renderer.resize(width, height)?;
        Ok(())
    }

    /// What the errors activity shaded over the atlas: generations, tiles, groups, bytes
    /// read back, and the median GPU time of a generation.
    pub fn errors_report(&self) -> serde_json::Value {
        let e = self.atlas.shaded();
        serde_json::json!({
            "generations": e.generations,
            "tiles_shaded": e.tiles,
            "groups_shaded": e.groups,
            "bytes_read_back": e.bytes_read_back,
            "median_gpu_ms": crate::app::outputs::median(&e.gpu_ms),
        })
    }

    /// Why the errors activity stopped, if it failed.
    pub fn failure(&self) -> Option<String> {
        self.atlas.failure()
    }

    /// Test hook: the errors activity fails as if the device were lost at block-error
    /// generation `n` (`--inject-fault errors-device-lost:N`).
    pub fn inject_device_lost_at(&self, n: u64) {
        self.atlas.inject_device_lost_at(n);
    }

    /// How the errors generations are paced: the largest share of wall time they take
    /// (`--update-share`), and whether two may be in flight (`--error-pacing`).
    pub fn pace_errors(&self, common: &CommonArgs) {
        self.atlas.set_update_share(common.update_share);
        self.atlas.set_pacing(common.error_pacing, &self.device);
    }

    /// Bytes of the heightfield atlas (heights and deviations) on the device.
    pub fn atlas_bytes(&self) -> u64 {
        self.atlas.bytes()
    }

    /// The most generations the errors activity had in flight at once.
    pub fn errors_in_flight(&self) -> u64 {
        self.atlas.most_in_flight()
    }

    /// What the errors generations shaded so far.
    pub fn errors_shaded(&self) -> crate::errors::atlas::ErrorsShaded {
        self.atlas.shaded()
    }

    pub fn report(&self) -> serde_json::Value {
        let validation = self.device.instance.validation;
        let up = self.atlas.uploaded();
        serde_json::json!({
            "device": self.device.name,
            "atlas_layers": self.atlas.layer_count(),
            "frames_drawn": self.frames,
            "tiles_uploaded": up.tiles,
            "uploaded_mb": up.bytes as f64 / f64::from(1u32 << 20),
            "upload_generations": up.generations,
            "tiles_without_a_layer": up.dropped,
            "frames_missing_blocks": self.frames_missing_blocks,
            "hidden_parts_per_frame": self.hidden_parts_total as f64 / self.frames.max(1) as f64,
            "occlusion": self.occlusion,
            "occluded_blocks_per_frame": self.occluded_blocks as f64 / self.frames.max(1) as f64,
            "draw_ms_per_frame": 1e3 * self.drawing.as_secs_f64() / self.frames.max(1) as f64,
            "errors": self.errors_report(),
            "lighting": {
                "texels": [self.lighting.map.image.extent.width, self.lighting.map.image.extent.height],
                "samples_per_texel": self.lighting.samples_per_texel(),
                "heights_samples_apart": self.lighting.source().stride,
                "shadows": self.lighting.map.sun().is_some(),
                "unreadable": self.no_shadows,
                "last_draw_ms": self.lighting.map.last_ms(),
            },
            "validation": validation,
            "validation_messages": validation.then(|| self.device.instance.validation_messages()),
        })
    }
}

/// The world heights the root blocks span, from the top tiles, which a settled frame
/// holds; `None` while any is missing.
fn top_tiles_range(streamer: &Streamer) -> Option<[f32; 2]> {
    let grid = &streamer.grid;
    let root = crate::stream::cache::root_lod(grid);
    let [nx, nz] = grid.tiles_at(grid.top);
    let mut range: Option<[f32; 2]> = None;
    for tz in 0..nz {
        for tx in 0..nx {
            let top = streamer.cache.peek(crate::stream::cache::serving_tile(grid, root, tx, tz))?;
            let b = top.block(grid, root, tx, tz);
            let [lo, hi] = [b.lo, b.hi].map(|h| (f64::from(h) * grid.height_scale) as f32);
            range = Some(range.map_or([lo, hi], |[a, c]| [a.min(lo), c.max(hi)]));
        }
    }
    range
}

/// The terrain's world heights for the colour ramp, sea level and default view: those
/// of every sample, which `prepare` records (`Meta::raw_range`), so that they are the
/// same terrain's in memory; an archive written before that gives its root blocks'
/// ([`top_tiles_range`]).
pub(crate) fn height_range(streamer: &Streamer, meta: &Meta) -> Option<HeightRange> {
    let world = match meta.raw_range {
        Some(raw) => raw.map(|h| (f64::from(h) * streamer.grid.height_scale) as f32),
        None => top_tiles_range(streamer)?,
    };
    Some(HeightRange { world, absolute: meta.georef.absolute_heights })
}

/// Reads the top tiles (a view of the whole terrain from high above, nothing split) and
/// returns the terrain's heights ([`height_range`]). Without the tiles nothing can be
/// drawn: an error naming what failed (exit 2).
pub(crate) fn top_tiles(streamer: &mut Streamer, meta: &Meta) -> anyhow::Result<HeightRange> {
    let grid = streamer.grid;
    let [wx, wz] = grid.world_extent();
    let high = 2.0 * wx.max(wz) + 1.0;
    let overview = View::look_at(
        DVec3::new(wx / 2.0, high, wz / 2.0),
        DVec3::new(wx / 2.0, 0.0, wz / 2.0 + 1.0),
        60.0,
        64,
        64,
        1.0,
    );
    settle(streamer, |_| overview, f32::MAX);
    let held = top_tiles_range(streamer).is_some();
    let range = height_range(streamer, meta).filter(|_| held).ok_or_else(|| {
        let why = streamer.first_failure.clone().unwrap_or_else(|| {
            let grid = &streamer.grid;
            let top = crate::stream::cache::tile_bytes_estimate(grid, grid.top) as f64 / f64::from(1 << 20);
            format!(
                "the cache ({:.0} MB) cannot hold them (the top tile takes about {top:.1} MB decoded with blocks of {} vertices a side)",
                streamer.cache.budget() as f64 / f64::from(1 << 20),
                grid.block_quads + 1
            )
        });
        anyhow::Error::from(InputError(format!("the archive's top tiles could not be read: {why}")))
    })?;
    if meta.raw_range.is_none() {
        eprintln!(
            "vkterrain: note: the archive records no height range (written before it did): colours and the \
             default view follow its top tiles' heights, {} to {}; `vkterrain prepare` it again to match the \
             terrain drawn in memory",
            range.world[0], range.world[1]
        );
    }
    Ok(range)
}

/// The grid of an archive as the options frame it: `--spacing` and `--height-scale`
/// override the archive's own, and say so (as the loader does for files); blocks of
/// `block` vertices a side (`--block`).
pub(crate) fn streamed_grid(
    archive: &Archive,
    frame: &crate::app::cli::FrameArgs,
    block: u32,
) -> Result<Grid, InputError> {
    let mut grid = Grid::from_meta(&archive.meta).with_block(block).map_err(InputError)?;
    // (A file prepared on the fly already has them: nothing to say.)
    if let Some(s) = frame.spacing.filter(|s| [f64::from(s.x), f64::from(s.z)] != grid.spacing) {
        eprintln!(
            "vkterrain: note: spacing {} x {} m from --spacing, not the archive's {} x {}",
            s.x, s.z, grid.spacing[0], grid.spacing[1]
        );
        grid.spacing = [f64::from(s.x), f64::from(s.z)];
    }
    if let Some(h) = frame.height_scale.filter(|h| f64::from(*h) != grid.height_scale) {
        eprintln!("vkterrain: note: height scale {h} from --height-scale, not the archive's {}", grid.height_scale);
        grid.height_scale = f64::from(h);
    }
    Ok(grid)
}

/// An archive whose reads (on the IO thread) are recorded in a trace, one span a tile.
struct TracedSource {
    archive: Arc<Archive>,
    trace: Trace,
}

impl TileSource for TracedSource {
    fn read(&self, key: TileKey) -> Result<Option<(crate::input::archive::tile::Tile, u64)>, String> {
        let t0 = Instant::now();
        let read = TileSource::read(&*self.archive, key);
        let args = match &read {
            Ok(Some((_, bytes))) => serde_json::json!({"level": key.level, "tx": key.tx, "tz": key.tz, "bytes": bytes}),
            Ok(None) => serde_json::json!({"level": key.level, "tx": key.tx, "tz": key.tz, "absent": true}),
            Err(e) => serde_json::json!({"level": key.level, "tx": key.tx, "tz": key.tz, "failed": e}),
        };
        self.trace.complete(IO_TID, "read tile", t0, Instant::now(), args);
        read
    }
}

/// A streamer for `archive` whose host cache of `cache_mb` never holds more tiles than an
/// atlas of `gpu_mb` has layers (`device_limit`: the device's array layers), so that
/// every tile a frame draws from has a layer. Its IO thread's reads go into `trace`.
pub(crate) fn atlas_bound_streamer(
    archive: Arc<Archive>,
    grid: Grid,
    cache_mb: u32,
    gpu_mb: u32,
    device_limit: u32,
    trace: &Trace,
) -> anyhow::Result<Streamer> {
    let layers = HeightAtlas::layers_for(&grid, u64::from(gpu_mb) << 20, device_limit);
    if layers == 0 {
        return Err(InputError(format!(
            "--gpu-mb {gpu_mb}: holds no atlas layer ({} bytes a tile)",
            HeightAtlas::layer_bytes(&grid)
        ))
        .into());
    }
    let source: Arc<dyn TileSource> = match trace.enabled() {
        true => Arc::new(TracedSource { archive, trace: trace.clone() }),
        false => archive,
    };
    let mut streamer = Streamer::new(source, grid, cache_mb as usize * (1 << 20));
    streamer.limit_tiles(HeightAtlas::cache_tiles(layers));
    Ok(streamer)
}

/// Gives the streamer's per-block morph terms the threads `--traversal-threads` asks
/// for, else [`traversal_threads`]'s default for `device` (1 with none: a flight on the
/// host alone).
pub(crate) fn streamer_threads(
    streamer: &mut Streamer,
    asked: Option<u16>,
    device: Option<&Device>,
) -> anyhow::Result<()> {
    let threads = match device {
        Some(d) => traversal_threads(asked, d.properties.device_type),
        None => asked.map_or(1, usize::from),
    };
    streamer.set_threads(threads).map_err(|e| anyhow::anyhow!(e))
}

/// Frames at the view `at` gives (it may depend on the tiles held: a camera kept above
/// the ground) until the selection is within the bound and, with an errors activity,
/// takes every block's error from it, the IO thread and the errors activity settled
/// after each: the frame a viewer shows once the tiles of its first view are read. At most
/// enough rounds for one level a round (plus a few), so that a cache too small for the
/// view ends with the frame over the bound, counted, not in a loop.
pub(crate) fn settle(streamer: &mut Streamer, at: impl Fn(&Streamer) -> View, delta: f32) -> (View, Selection) {
    let rounds = 2 * (streamer.grid.top as usize + 4);
    let mut view = at(streamer);
    let mut sel = streamer.frame(&view, None, delta, 1.0);
    for _ in 1..rounds {
        // With an errors activity, settled also means every block's error came from it.
        let errors_missing = streamer.has_errors_activity() && sel.errors_from_tiles > 0;
        if (sel.within_bound() && !errors_missing) || streamer.stopped() {
            break;
        }
        streamer.settle();
        view = at(streamer);
        sel = streamer.frame(&view, None, delta, 1.0);
    }
    (view, sel)
}

/// Prints what `prepare` recorded about an archive's frame (how its spacing, height unit
/// and datum were decided, what was assumed), less what `frame` now sets, as a file's
/// load prints it; then applies `--heights` (spacing and height scale: [`streamed_grid`]).
/// The archive's frame with `--spacing` and `--height-scale` over it must stay within
/// [`crate::lod::heightfield::MAX_WORLD`], its extent and its heights, as a file's must
/// (exit 2 naming the options, not frames of NaN).
fn check_declared_frame(shown: &str, m: &Meta, frame: &crate::app::cli::FrameArgs) -> Result<(), InputError> {
    let declared = crate::prepare::Frame {
        spacing: frame.spacing.map_or(m.spacing, |s| [s.x, s.z]),
        height_scale: frame.height_scale.unwrap_or(m.height_scale),
        georef: crate::lod::heightfield::Georef::default(),
        void_samples: 0,
    };
    let given = "(check --spacing and --height-scale)";
    crate::prepare::check_frame(shown, &declared, m.width, m.height).map_err(|e| InputError(format!("{e} {given}")))?;
    let top = m.raw_range.map_or(0.0, |[lo, hi]| lo.abs().max(hi.abs())) * declared.height_scale;
    if top.is_nan() || top > crate::lod::heightfield::MAX_WORLD {
        return Err(InputError(format!(
            "{shown}: heights reach {top:e} world units at height scale {:e}: beyond {:e} {given}",
            declared.height_scale,
            crate::lod::heightfield::MAX_WORLD
        )));
    }
    Ok(())
}

fn declare_frame(shown: &str, archive: &mut Archive, frame: &crate::app::cli::FrameArgs) {
    let mut notes = archive.meta.georef.notes.clone();
    georef::drop_overridden(&mut notes, &frame.declared());
    notes.extend(frame.heights.and_then(|h| georef::declare_heights(&mut archive.meta.georef, h)));
    for n in notes {
        eprintln!("vkterrain: note: {shown}: {n}");
    }
}

/// The tiles of the terrain `terrain` names when a command draws it streamed: with
/// `stream`, or when its grid is larger than one image (`max_side()`, the device's). A
/// terrain file, or the built-in terrain, is cut into tiles in memory; a file cut so
/// comes with the stop signals' handlers its cutting installed
/// (`tiles_of_file` in `app::prepare`), for a caller with none of its own to poll.
pub fn streamed_archive(
    terrain: &TerrainArgs,
    stream: bool,
    max_side: impl FnOnce() -> usize,
) -> anyhow::Result<Option<(Arc<Archive>, Option<Stop>)>> {
    let hole = terrain.voids == crate::input::load::VoidMode::Hole;
    let Some(path) = terrain.heightmap.as_deref() else {
        if !stream {
            return Ok(None);
        }
        // (The built-in terrain has no voids: `--voids hole` changes nothing.)
        return Ok(Some((Arc::new(crate::app::prepare::tiles_of_builtin(terrain)?), None)));
    };
    // Before anything opens it (sniffing the archive, reading a raster's header): a FIFO
    // would block in open().
    if !crate::input::archive::bytes::is_url(path) {
        crate::input::regular_file(path).map_err(InputError)?;
    }
    if !Archive::is_archive(path) {
        // A file larger than one image (or any, with `stream`) is cut into tiles: one
        // path for every size.
        let too_big = || {
            // A raw file's size is the one given (GDAL cannot read its header).
            let size = terrain.raw_size.map(|(w, h)| (w as usize, h as usize));
            size.or_else(|| crate::app::prepare::raster_size(path)).is_some_and(|(w, h)| {
                let (n, roots) = crate::lod::heightfield::grid_cover(w, h);
                let side = roots.into_iter().max().unwrap_or(1) * (1 << n) + 1;
                // Every Vulkan device takes 4096 (the spec's minimum): no device is asked.
                side > 4096 && side > max_side()
            })
        };
        if !(stream || too_big()) {
            return Ok(None);
        }
        // Cut with its void mask when voids are drawn as holes.
        let (archive, stop) = crate::app::prepare::tiles_of_file(path, terrain)?;
        return Ok(Some((Arc::new(archive), Some(stop))));
    }
    if terrain.raw_size.is_some() {
        return Err(InputError(format!(
            "{}: --raw-size is for raw height files; an archive knows its own size",
            path.display()
        ))
        .into());
    }
    let mut archive = Archive::open(path).map_err(|e| InputError(e.to_string()))?;
    crate::app::prepare::check_void_mask(&crate::input::archive::bytes::shown(path), &archive.meta, terrain.voids)?;
    // Drawn with its voids filled: the tiles' masks are left unread.
    archive.meta.void_mask &= hole;
    // With `--voids hole` an archive is drawn from its tiles whatever its size: in memory
    // an archive's voids are filled.
    if !stream && !hole && (archive.grid_side() <= 4096 || archive.grid_side() <= max_side()) {
        return Ok(None);
    }
    let shown = crate::input::archive::bytes::shown(path);
    check_declared_frame(&shown, &archive.meta, &terrain.frame)?;
    declare_frame(&shown, &mut archive, &terrain.frame);
    Ok(Some((Arc::new(archive), None)))
}

/// `errors` over the atlas: the first view's tiles read and uploaded, then `repeat`
/// generations of block errors, each for a camera a hundredth of a sample further along
/// x than the one before (a new generation each, unless the view holds no terrain),
/// waited for; their count, wall and GPU times and what the last one shaded (per
/// generation, as the in-memory `errors` reports), as JSON.
pub(crate) fn errors_over_atlas(
    archive: &Arc<Archive>,
    device: &Arc<Device>,
    (frame, block): (&crate::app::cli::FrameArgs, u32),
    camera: &crate::app::cli::CameraArgs,
    (repeat, mode): (u64, crate::lod::gie::ErrorMode),
    (cache_mb, gpu_mb): (u32, u32),
    dump: Option<&std::path::Path>,
) -> anyhow::Result<serde_json::Value> {
    let grid = streamed_grid(archive, frame, block)?;
    let layers = device.properties.limits.max_image_array_layers;
    let mut streamer = atlas_bound_streamer(archive.clone(), grid, cache_mb, gpu_mb, layers, &Trace::off())?;
    streamer.error_mode = mode;
    let range = top_tiles(&mut streamer, &archive.meta)?;
    let atlas = HeightAtlas::new(device, &grid, u64::from(gpu_mb) << 20).map_err(|e| InputError(e.to_string()))?;
    streamer.attach(Box::new(atlas.feed()), HeightAtlas::cache_tiles(atlas.layer_count()));
    let (w, h) = camera.frustum.size.unwrap_or((1280, 720));
    crate::app::cli::check_image_size(device, "--size", (w, h))?;
    let near = near_plane_for(grid.spacing[0].min(grid.spacing[1]) as f32);
    let extent = grid.world_extent().map(|e| e as f32);
    let (position, look_at) =
        camera.view_points(|| view_of_box(extent, range.world, camera.frustum.fovy, w, h, near))?;
    let view = |i: u64| {
        let p = position.as_dvec3() + DVec3::X * (i as f64 * grid.spacing[0] * 0.01);
        View::look_at(p, look_at.as_dvec3(), camera.frustum.fovy, w, h, near)
    };
    let (_, first) = settle(&mut streamer, |_| view(0), 1.0);
    // Whatever the last settling frame asked for is shaded before the repeats start.
    streamer.settle();
    // The generation at the given camera, as in memory's dump (its first repeat's).
    let at_start = crate::stream::streamer::TileGate::errors(&atlas.feed());
    // From here: the repeats' own generations, one each (none if no tile the view
    // reaches has a level above 0).
    let before = atlas.shaded();
    let mut times = vec![];
    for i in 1..=repeat {
        let (g, t) = (atlas.shaded().generations, Instant::now());
        let sel = streamer.frame(&view(i), None, 1.0, 1.0);
        streamer.ask_errors(&view(i), &sel);
        streamer.settle();
        if atlas.shaded().generations > g {
            times.push(t.elapsed().as_secs_f64() * 1e3);
        }
    }
    if let Some(e) = atlas.failure() {
        return Err(anyhow::anyhow!("the errors activity stopped: {e}"));
    }
    times.sort_by(f64::total_cmp);
    if let Some(path) = dump {
        // In the in-memory dump's layout.
        let l = crate::stream::draw::layout(&grid);
        let per_side = grid.tile_quads / grid.block_quads;
        let errors = at_start.unwrap_or_default();
        let bytes: Vec<u8> =
            errors.packed(l.root_lod(), l.roots, per_side).iter().flat_map(|v| v.to_le_bytes()).collect();
        crate::app::outputs::write_atomic(path, |tmp| {
            std::fs::write(tmp, &bytes).map_err(|e| anyhow::anyhow!("{}: {e}", path.display()))
        })?;
    }
    let shaded = atlas.shaded();
    let generations = shaded.generations - before.generations;
    // The last generation's figures, if a repeat shaded one.
    let last = shaded.last.filter(|_| generations > 0);
    let layout = crate::stream::draw::layout(&grid);
    Ok(serde_json::json!({
        "streamed": true,
        // The samples the blocks cover, as every `errors` and `render` reports them.
        "grid": layout.roots.map(|r| (r << layout.n) + 1),
        "roots": layout.roots,
        "block": grid.block_quads + 1,
        "error_mode": mode.as_str(),
        "atlas_layers": atlas.layer_count(),
        "tiles_held": streamer.cache.len(),
        "blocks_bounded_by_errors": first.drawn_bounded_by().0,
        "generations": generations,
        "tiles_shaded": last.map(|l| l.tiles),
        "groups_shaded": last.map(|l| l.groups),
        "readback_bytes": last.map(|l| l.bytes_read_back),
        "update_ms": times.get(times.len() / 2),
        "update_ms_min": times.first(),
        "update_gpu_ms": crate::app::outputs::median(&shaded.gpu_ms[before.gpu_ms.len()..]),
        "repeat": repeat,
    }))
}

/// One frame of an archive drawn streamed (`render` over an archive larger than one
/// image, or with `--stream`): what to draw and with what budgets.
pub struct ArchiveFrame<'a> {
    pub archive: Arc<Archive>,
    pub device: Arc<Device>,
    pub common: &'a CommonArgs,
    pub delta: f32,
    pub fog: f32,
    pub cache_mb: u32,
    pub gpu_mb: u32,
    /// Blocks tinted by their LOD.
    pub colour_by_lod: bool,
    /// A plain background instead of the sky.
    pub background: Option<[f32; 3]>,
    /// Also make the drawn mesh (`render --export-mesh`), from the tiles the frame held.
    pub export_mesh: bool,
    /// Stop signals to obey between the frame's steps (a run with handlers installed,
    /// which then no longer end it by themselves), exiting with 128 + the signal.
    pub stop: Option<&'a Stop>,
    /// How blocks choose their LOD (`--lod`).
    pub lod: LodChoice,
    /// Where the frame's normals come from (`--shading`).
    pub normals: crate::draw::blocks::NormalSource,
    /// Deferred or forward shading (`--pixels`).
    pub pixels: crate::draw::blocks::PixelPass,
    /// Base and detail textures (`--texture`, `--detail`).
    pub textures: &'a crate::app::cli::TextureArgs,
    /// Blocks drawn by rays (`--raycast`).
    pub raycast: crate::draw::raycast::Raycast,
}

/// The streamed rule for a `--lod` choice (the in-memory rings' factor).
pub(crate) fn streamed_lod(lod: LodChoice) -> StreamedLod {
    match lod {
        LodChoice::Error => StreamedLod::Error,
        LodChoice::Full => StreamedLod::Full,
        LodChoice::Distance => StreamedLod::Distance { factor: DISTANCE_FACTOR },
    }
}

/// Ends the process as the signal would have, once a stop was asked for.
pub(crate) fn exit_if_stopped(stop: Option<&Stop>) {
    if let Some(s) = stop.filter(|s| s.requested()) {
        eprintln!("vkterrain: interrupted: no output written");
        std::process::exit(s.exit_code());
    }
}

/// What [`render_archive`] drew: the pixels and the JSON facts.
pub struct ArchiveRender {
    pub width: u32,
    pub height: u32,
    pub pixels: Vec<u8>,
    pub report: serde_json::Value,
    /// The blocks as drawn (stitched), in the archive's block layout, and the camera, in
    /// the world (`render --audit`).
    pub drawn: Vec<crate::lod::block::DrawBlock>,
    pub layout: crate::lod::block::BlockLayout,
    pub view: View,
    /// The drawn mesh in world units, when asked ([`ArchiveFrame::export_mesh`]).
    pub mesh: Option<crate::lod::mesh::DrawnMesh>,
}

/// Draws one frame of an archive through the streaming path: the tiles the view needs
/// read into a host cache of `cache_mb`, uploaded into an atlas of `gpu_mb`, the blocks
/// drawn from it (plain shading). The frame waits for its tiles, as a viewer's first frame
/// does; where the cache cannot hold them it is drawn over the bound and says so.
pub fn render_archive(f: ArchiveFrame) -> anyhow::Result<ArchiveRender> {
    let grid = streamed_grid(&f.archive, &f.common.terrain.frame, f.common.block.k)?;
    let (w, h) = f.common.view.frustum.size.unwrap_or((1280, 720));
    crate::app::cli::check_image_size(&f.device, "--size", (w, h))?;
    let layers = f.device.properties.limits.max_image_array_layers;
    let mut streamer = atlas_bound_streamer(f.archive.clone(), grid, f.cache_mb, f.gpu_mb, layers, &Trace::off())?;
    streamer.morph = morph_rule(f.common.lod.morph.setting);
    streamer.error_mode = f.common.error_mode.mode;
    streamer.refresh_at = f.common.refresh_at;
    streamer.lod = streamed_lod(f.lod);
    streamer_threads(&mut streamer, f.common.lod.traversal_threads, Some(&f.device))?;
    let near = near_plane_for(grid.spacing[0].min(grid.spacing[1]) as f32);
    let extent = grid.world_extent();
    // The top tiles first: the default view frames the terrain's height range.
    let range = top_tiles(&mut streamer, &f.archive.meta)?;
    exit_if_stopped(f.stop);
    let (position, look_at) = f
        .common
        .view
        .view_points(|| view_of_box(extent.map(|e| e as f32), range.world, f.common.view.frustum.fovy, w, h, near))?;
    let view = View::look_at(position.as_dvec3(), look_at.as_dvec3(), f.common.view.frustum.fovy, w, h, near);
    let warm = Instant::now();
    // The stats keep the top tiles' reads (this frame's too); frames and the worst factor
    // count from here.
    let frames_before = streamer.stats.frames;
    streamer.stats.worst_factor = 1.0;
    settle(&mut streamer, |_| view, f.delta);
    exit_if_stopped(f.stop);
    let mut gpu = GpuFrames::new(f.device.clone(), &mut streamer, f.gpu_mb, range, (w, h), &Trace::off())?;
    gpu.pace_errors(f.common);
    // Again with the atlas attached: the blocks' errors from the errors activity.
    let (_, sel) = settle(&mut streamer, |_| view, f.delta);
    exit_if_stopped(f.stop);
    let settle_ms = warm.elapsed().as_secs_f64() * 1e3;
    gpu.set_normals(f.normals);
    gpu.set_pixels(f.pixels);
    let m = &f.archive.meta;
    gpu.set_textures(&f.textures.load_over(&m.georef, (m.width, m.height))?, f.textures)?;
    gpu.fog = f.fog;
    gpu.colour_by_lod = f.colour_by_lod;
    gpu.background = f.background;
    gpu.raycast = f.raycast;
    gpu.occlusion = f.common.occlusion != Some(crate::app::cli::OnOff::Off);
    gpu.sun(f.common.sun.0)?;
    gpu.draw(&streamer, &grid, &view, &sel, None)?;
    exit_if_stopped(f.stop);
    let missing = gpu.frames_missing_blocks > 0;
    let report = serde_json::json!({
        "width": w,
        "height": h,
        "streamed": true,
        "delta": f.delta,
        "blocks": gpu.drawn.blocks,
        "triangles": gpu.drawn.triangles,
        "hidden_parts": gpu.drawn.hidden_parts,
        "hidden_triangles": gpu.drawn.hidden_parts * crate::stream::draw::layout(&grid).triangles_per_part(),
        // What occlusion culling did (as in memory: null when off).
        "occlusion": gpu.last_occlusion,
        "draw_calls": gpu.drawn.draw_calls,
        "raycast": crate::app::cli::value_name(f.raycast),
        "raycast_blocks": gpu.drawn.raycast_blocks,
        "gpu_ms": gpu.drawn.gpu_ms,
        "within_bound": sel.within_bound() && !missing,
        "blocks_over_bound": sel.over_bound,
        "worst_factor": sel.worst_factor,
        "stitch_splits": sel.stitch_splits,
        // Of the blocks drawn (the rest: LOD 0, or the top tile's coarser blocks).
        "blocks_bounded_by_errors": sel.drawn_bounded_by().0,
        "blocks_bounded_by_tiles": sel.drawn_bounded_by().1,
        "errors_generation": sel.errors_generation,
        "lod": format!("{:?}", f.lod).to_lowercase(),
        "error_mode": f.common.error_mode.mode.as_str(),
        "shading": crate::app::cli::value_name(f.normals),
        // What drew the frame: forward where asked, or where deferred cannot (see
        // StreamedRenderer::deferred).
        "pixels": if gpu.drawn.deferred { "deferred" } else { "forward" },
        "morph": f.common.lod.morph.on(),
        "morphing": sel.morphing,
        "traversal_threads": streamer.threads(),
        "blocks_missing_a_layer": missing,
        "frames_to_settle": streamer.stats.frames - frames_before,
        "settle_ms": settle_ms,
        "cache_mb": f.cache_mb,
        // Every tile read for the frame (the top tiles first, then the view's).
        "stats": streamer.stats,
        "first_failure": streamer.first_failure,
        "gpu": gpu.report(),
        "device": f.device.name,
        "validation_messages": f.device.instance.validation_messages(),
        "camera": [position.x, position.y, position.z],
        "look_at": [look_at.x, look_at.y, look_at.z],
        "peak_resident_mb": crate::app::outputs::peak_resident_mb(),
    });
    let (pixels, drawn) = (std::mem::take(&mut gpu.last), sel.stitched);
    let layout = crate::stream::draw::layout(&grid);
    // The blocks whole (parts left out included, as in memory), their vertices from the
    // held tiles, which are the drawn ones.
    let mesh = f.export_mesh.then(|| {
        let resident = crate::stream::draw::Resident { grid: &grid, cache: &streamer.cache };
        let world = |x: i64, z: i64, raw: f32| {
            let [wx, wz] = grid.world_xz(x as f64, z as f64);
            [wx as f32, (f64::from(raw) * grid.height_scale) as f32, wz as f32]
        };
        let hole = |x: i64, z: i64| resident.is_hole(x, z);
        let surface = crate::lod::mesh::MeshSurface {
            last: [grid.width as i64 - 1, grid.height as i64 - 1],
            world: &world,
            hole: grid.holes.then_some(&hole as &dyn Fn(i64, i64) -> bool),
        };
        crate::lod::mesh::drawn_mesh_of(&resident, &layout, &drawn, &surface)
    });
    // The block grid as in memory: `roots` squares of 2^n + 1 samples sharing borders.
    let mut report = report;
    report["grid"] = serde_json::json!(layout.roots.map(|r| (r << layout.n) + 1));
    report["roots"] = serde_json::json!(layout.roots);
    Ok(ArchiveRender { width: w, height: h, pixels, report, drawn, layout, view, mesh })
}

/// Marks the blocks of a frame that are ray-cast with `mode` (`--raycast`), by the
/// in-memory rule ([`crate::draw::raycast::Choice`]): blocks that neither morph nor
/// follow a coarser edge, inside the true extent, whose boxes (their vertices' range,
/// from their tile's summary) are cheap enough in rays for `auto`. `under`: the camera
/// can see the surface from below, which rays do not reproduce: none is ray-cast.
/// Returns the pixels the chosen blocks' boxes cover (the rays a deferred frame casts).
fn choose_raycast(
    grid: &Grid,
    cache: &crate::stream::cache::HostCache,
    (anchor, cam): ([i64; 2], &crate::lod::camera::Camera),
    blocks: &mut [crate::stream::draw::StreamedBlock],
    (mode, ring_triangles, under): (crate::draw::raycast::Raycast, u64, bool),
) -> f64 {
    use crate::draw::raycast::{Choice, Raycast};
    if mode == Raycast::Off || under {
        return 0.0;
    }
    let layout = crate::stream::draw::layout(grid);
    // The range of a block's vertices and resolved corners; `None` before its tile is held.
    let range = |b: &crate::lod::block::DrawBlock| {
        let tile = cache.peek(crate::stream::cache::serving_tile(grid, b.lod, b.bx, b.bz))?;
        let s = tile.block(grid, b.lod, b.bx, b.bz);
        let corners = b.corner_raw.map(f32::from_bits);
        Some(corners.into_iter().fold([s.lo, s.hi], |[lo, hi], c| [lo.min(c), hi.max(c)]))
    };
    let world_box = |b: &crate::lod::block::DrawBlock| {
        let (ox, oz) = b.origin(&layout);
        let side = layout.block_samples(b.lod) as i64;
        let [lo, hi] = range(b).unwrap_or([0.0, 0.0]).map(|h| (f64::from(h) * grid.height_scale) as f32);
        let at = |x: i64, z: i64| {
            [((x - anchor[0]) as f64 * grid.spacing[0]) as f32, ((z - anchor[1]) as f64 * grid.spacing[1]) as f32]
        };
        let ([x0, z0], [x1, z1]) = (at(ox as i64, oz as i64), at(ox as i64 + side, oz as i64 + side));
        (glam::Vec3::new(x0, lo, z0), glam::Vec3::new(x1, hi, z1))
    };
    let choice = Choice {
        mode,
        layout: &layout,
        extent: [grid.width as u32, grid.height as u32],
        world_box: Box::new(world_box),
        cam,
        ring_triangles,
    };
    let mut pixels = 0.0;
    for b in blocks.iter_mut() {
        if choice.casts(&b.block) {
            b.raycast = range(&b.block);
            pixels += choice.box_pixels(&b.block);
        }
    }
    pixels
}

/// Whether a camera at `p` can see the surface from below, as the in-memory ray-caster
/// asks (`BlocksRenderer::raycast_choice`): under the ground (the highest of the four
/// samples around it, from the held tiles), or beyond the terrain's edge lower than its
/// top (`top`, world units), looking in through the cut edge.
fn sees_the_underside(grid: &Grid, streamer: &Streamer, p: DVec3, top: f32) -> bool {
    let [sx, sz] = grid.sample_of(p.x, p.z);
    let beyond = sx < 0.0 || sz < 0.0 || sx > (grid.width - 1) as f64 || sz > (grid.height - 1) as f64;
    if beyond {
        return p.y < f64::from(top);
    }
    let corners = [(sx.floor(), sz.floor()), (sx.ceil(), sz.floor()), (sx.floor(), sz.ceil()), (sx.ceil(), sz.ceil())];
    let ground = corners.into_iter().filter_map(|(x, z)| {
        let [wx, wz] = grid.world_xz(x, z);
        streamer.ground(wx, wz)
    });
    // Before any tile is held, assume the worst: nothing is ray-cast.
    ground.fold(None, |m: Option<f64>, g| Some(m.map_or(g, |m| m.max(g)))).is_none_or(|g| p.y < g)
}

/// A frame rate the flight can be paced at: 0.1 to 10,000 frames a second.
fn parse_fps(s: &str) -> Result<f32, String> {
    let v = crate::app::cli::positive(s)?;
    if !(0.1..=10_000.0).contains(&v) {
        return Err(format!("'{s}': from 0.1 to 10000 frames a second"));
    }
    Ok(v)
}

/// Bytes this process has read from storage (`read_bytes` of /proc/self/io).
fn disk_bytes_read() -> Option<u64> {
    let io = std::fs::read_to_string("/proc/self/io").ok()?;
    io.lines().find_map(|l| l.strip_prefix("read_bytes: ")).and_then(|v| v.trim().parse().ok())
}

/// Asks the kernel to drop the file's pages from the page cache.
fn drop_from_page_cache(path: &std::path::Path) -> std::io::Result<()> {
    use std::os::fd::AsRawFd;
    let file = std::fs::File::open(path)?;
    // SAFETY: the descriptor is open for the duration of the call; fadvise only advises.
    let rc = unsafe { libc::posix_fadvise(file.as_raw_fd(), 0, 0, libc::POSIX_FADV_DONTNEED) };
    if rc != 0 {
        return Err(std::io::Error::from_raw_os_error(rc));
    }
    Ok(())
}

/// `v` as a person reads it: plain below 10^7, in exponent form above (1e30, not 31 digits).
fn readable(v: f32) -> String {
    if v.abs() < 1e7 {
        format!("{}", (v * 10.0).round() / 10.0)
    } else {
        format!("{v:e}")
    }
}

/// Where a flight is `d` world units along a line of `length` (from its start), and the
/// way it heads (1 out, -1 back): it turns at each end rather than leaving the terrain.
fn along_line(d: f64, length: f64) -> (f64, f64) {
    let u = d.rem_euclid(2.0 * length);
    if u <= length {
        (u, 1.0)
    } else {
        (2.0 * length - u, -1.0)
    }
}

pub fn stream(args: &StreamArgs) -> anyhow::Result<()> {
    let d = &args.device;
    if args.gpu_mb.is_none() && (d.validation.is_some() || d.gpu.is_some() || d.queues != crate::vk::QueueRequest::Auto)
    {
        return Err(InputError(
            "--validation, --gpu and --queues are for frames drawn on the GPU: give --gpu-mb too".into(),
        )
        .into());
    }
    let paper = args.error_mode.mode == crate::lod::gie::ErrorMode::Paper;
    if args.gpu_mb.is_none() && paper {
        return Err(InputError(
            "--error-mode paper: the paper's errors are shaded by the errors activity on the GPU: give --gpu-mb too"
                .into(),
        )
        .into());
    }
    if let Some(out) = &args.out {
        if !crate::app::outputs::is_png(out) {
            return Err(InputError(format!("--out {}: the output must be a .png file", out.display())).into());
        }
        crate::app::outputs::check_outputs(
            &[("--out", Some(out))],
            &[("the terrain", args.terrain.heightmap.as_deref())],
        )?;
    }
    let shown = args.terrain.name();
    let (archive, _) = streamed_archive(&args.terrain, true, || usize::MAX)?.expect("a terrain drawn from tiles");
    let grid = streamed_grid(&archive, &args.terrain.frame, args.block.k)?;
    let local_archive = args.terrain.heightmap.as_deref().filter(|p| !archive.held_in_memory() && !is_url(p));
    match (args.cold, local_archive) {
        (false, _) => {}
        (true, Some(path)) => drop_from_page_cache(path)
            .map_err(|e| InputError(format!("{shown}: dropping it from the page cache: {e}")))?,
        (true, None) if args.terrain.heightmap.as_deref().is_some_and(is_url) => {
            eprintln!("vkterrain: note: --cold: {shown} is a URL, with no local page cache to drop")
        }
        (true, None) => eprintln!("vkterrain: note: --cold: {shown} is cut into tiles in memory, not read from disk"),
    }
    let (w, h) = args.size;
    let extent = grid.world_extent();
    // From near one corner along the diagonal, looking ahead and a little down.
    let start = DVec3::new(0.05 * extent[0], 0.0, 0.05 * extent[1]);
    let along = DVec3::new(0.9 * extent[0], 0.0, 0.9 * extent[1]);
    let dir = along.normalize();
    let line = along.length();
    let fps = f64::from(args.fps);
    let speed = f64::from(args.speed);
    let distance = speed * args.frames as f64 / fps;
    if speed / fps > line {
        return Err(InputError(format!(
            "--speed {}: {} units a frame at {fps} fps, longer than the flight's line across {shown} ({line:.0} units)",
            readable(args.speed),
            readable((speed / fps) as f32)
        ))
        .into());
    }
    let turns = (distance / line).floor() as u64;
    if turns > 0 {
        eprintln!(
            "vkterrain: note: the flight ({distance:.0} units) is longer than its line across {shown} ({line:.0} units): it turns back at the ends ({})",
            if turns == 1 { "once".to_string() } else { format!("{turns} times") }
        );
    }
    // Ctrl-C or SIGTERM ends the flight after the frame in hand; what was flown is
    // reported.
    let signals = Stop::install();
    let read_before = disk_bytes_read();
    eprintln!(
        "vkterrain: streaming {} ({} x {} samples, {} tile levels): {} frames at {fps} fps, {speed:.0} units/s, {} above the ground, cache {} MB",
        shown,
        grid.width,
        grid.height,
        grid.top + 1,
        args.frames,
        args.altitude,
        args.cache_mb
    );
    let device = match args.gpu_mb {
        Some(_) => {
            use crate::vk::{DeviceOptions, Instance, InstanceOptions};
            let instance =
                Instance::new(&InstanceOptions { validation: args.device.validation(), extensions: Vec::new() })?;
            let options = DeviceOptions { gpu: args.device.gpu.clone(), queues: args.device.queues, swapchain: false };
            let device = Device::new(instance, &options).map_err(crate::app::cli::option_error)?;
            crate::app::cli::check_image_size(&device, "--size", args.size)?;
            Some(device)
        }
        None => None,
    };
    let mut streamer = match (args.gpu_mb, &device) {
        (Some(mb), Some(d)) => {
            let layers = d.properties.limits.max_image_array_layers;
            atlas_bound_streamer(archive.clone(), grid, args.cache_mb, mb, layers, &Trace::off())?
        }
        _ => Streamer::new(archive.clone(), grid, args.cache_mb as usize * (1 << 20)),
    };
    streamer.morph = morph_rule(args.lod.morph.setting);
    streamer.error_mode = args.error_mode.mode;
    streamer.stop = Some(signals.flag().clone());
    streamer_threads(&mut streamer, args.lod.traversal_threads, device.as_deref())?;
    // The view at frame `f`, and the way it heads.
    let pose = |streamer: &Streamer, f: u64| {
        let (offset, way) = along_line(speed * f as f64 / fps, line);
        let (at, heading) = (start + dir * offset, dir * way);
        let ground = |p: DVec3| streamer.ground(p.x, p.z).unwrap_or(0.0);
        // Above the highest of the ground here and a little ahead (from the tiles held).
        let lookahead = heading * 4.0 * f64::from(args.altitude);
        let altitude = ground(at).max(ground(at + lookahead)) + f64::from(args.altitude);
        let position = DVec3::new(at.x, altitude, at.z);
        let target = position + heading * 1000.0 + DVec3::new(0.0, -1000.0 * 0.15, 0.0);
        (View::look_at(position, target, 45.0, w, h, 1.0), heading)
    };
    // As a viewer would: the top tiles (without which nothing can be drawn: refused, as
    // `render` refuses them, rather than a flight of empty frames), then the first
    // view's, are read before the flight starts.
    let warm = Instant::now();
    let range = match top_tiles(&mut streamer, &archive.meta) {
        Err(_) if signals.requested() => {
            // Stopped before the flight: what there is to say, as a flight's JSON says it.
            let mut json = serde_json::json!({
                "archive": &shown,
                "frames": 0,
                "warm_up": { "seconds": warm.elapsed().as_secs_f64(), "tiles_loaded": streamer.stats.tiles_loaded },
                "first_failure": streamer.first_failure,
                "degraded": false,
                "interrupted": true,
            });
            crate::app::outputs::TerrainFacts::of_archive(&archive.meta, &args.terrain.frame).merge_into(&mut json);
            crate::out!("{}", serde_json::to_string_pretty(&json)?)?;
            return Err(Interrupted::by(&signals, "while the top tiles were read: nothing flown").into());
        }
        r => r?,
    };
    settle(&mut streamer, |s| pose(s, 0).0, args.lod.delta);
    let warm_up_s = warm.elapsed().as_secs_f64();
    let mut gpu = match (args.gpu_mb, device) {
        (Some(mb), Some(device)) => {
            let mut g = GpuFrames::new(device, &mut streamer, mb, range, args.size, &Trace::off())?;
            // No `--sun` here: the default sun and its shadows, as the other commands draw.
            g.sun(Some(Sun::DEFAULT))?;
            // The first view's errors from the errors activity, now attached.
            settle(&mut streamer, |s| pose(s, 0).0, args.lod.delta);
            Some(g)
        }
        _ => None,
    };
    let warm_stats = streamer.stats.clone();
    streamer.stats.worst_factor = 1.0; // the flight's own worst
    let started = Instant::now();
    let period = Duration::from_secs_f64(1.0 / fps);
    let (mut blocks, mut morphing) = (0u64, 0u64);
    let mut selecting = Duration::ZERO;
    let mut altitude = 0.0;
    for f in 0..args.frames {
        if signals.requested() {
            break;
        }
        let (view, heading) = pose(&streamer, f);
        altitude = view.position.y;
        let ahead = View { position: view.position + heading * speed * 0.5, ..view };
        let t0 = Instant::now();
        let sel = streamer.frame(&view, Some(&ahead), args.lod.delta, 0.5);
        selecting += t0.elapsed();
        blocks += sel.blocks.len() as u64;
        morphing += sel.morphing as u64;
        if let Some(g) = gpu.as_mut() {
            g.draw(&streamer, &grid, &view, &sel, None)?;
        }
        // Pacing the flight to its frame rate (not synchronisation: nothing waits on it).
        let next = period.mul_f64((f + 1) as f64);
        if let Some(rest) = next.checked_sub(started.elapsed()) {
            std::thread::sleep(rest);
        }
    }
    let seconds = started.elapsed().as_secs_f64();
    // The flight's own figures: the warm-up's frames and tiles are reported apart.
    let mut flight = streamer.stats.clone();
    flight.frames -= warm_stats.frames;
    flight.frames_over_bound -= warm_stats.frames_over_bound;
    let StreamStats { frames, frames_over_bound, .. } = flight;
    let distinct_mb = flight.distinct_bytes as f64 / f64::from(1u32 << 20);
    let mut json = serde_json::json!({
        "archive": &shown,
        "frames": frames,
        "frames_over_bound": frames_over_bound,
        "frames_over_bound_share": frames_over_bound as f64 / frames as f64,
        "stats": flight,
        "warm_up": { "seconds": warm_up_s, "frames": warm_stats.frames, "tiles_loaded": warm_stats.tiles_loaded },
        "distance": distance,
        "line_length": line,
        "turns": turns,
        "cache_mb": args.cache_mb,
        "distinct_tiles_mb": distinct_mb,
        "distinct_over_cache": distinct_mb / f64::from(args.cache_mb),
        "disk_bytes_read": match (read_before, disk_bytes_read()) { (Some(a), Some(b)) => Some(b - a), _ => None },
        "peak_resident_mb": crate::app::outputs::peak_resident_mb(),
        "blocks_per_frame": blocks as f64 / frames as f64,
        "morph": args.lod.morph.on(),
        "block": grid.block_quads + 1,
        "error_mode": args.error_mode.mode.as_str(),
        "morphing_per_frame": morphing as f64 / frames as f64,
        "select_ms_per_frame": 1e3 * selecting.as_secs_f64() / frames as f64,
        "traversal_threads": streamer.threads(),
        "seconds": seconds,
        "last_altitude": altitude,
        "first_failure": streamer.first_failure,
        "degraded": streamer.first_failure.is_some(),
        "interrupted": signals.requested(),
        "gpu": gpu.as_ref().map(GpuFrames::report),
    });
    crate::app::outputs::TerrainFacts::of_archive(&archive.meta, &args.terrain.frame).merge_into(&mut json);
    match (gpu.as_ref(), args.out.as_ref()) {
        (Some(g), Some(out)) if g.last.is_empty() => {
            eprintln!("vkterrain: note: no frame was drawn: {} not written", out.display())
        }
        (Some(g), Some(out)) => {
            let (w, h) = args.size;
            crate::app::outputs::save_png(out, w, h, &g.last)?;
            eprintln!("vkterrain: last frame written to {}", out.display());
        }
        _ => {}
    }
    crate::out!("{}", serde_json::to_string_pretty(&json)?)?;
    if let Some(g) = gpu {
        // Every Vulkan object goes first: messages from their destruction count too.
        let messages = g.device.instance.messages.clone();
        drop(g);
        crate::app::cli::check_messages(&messages)?;
    }
    eprintln!(
        "vkterrain: {frames} frames, {frames_over_bound} over the bound ({:.1}%, worst {:.2}x delta); {} tiles loaded, {} distinct ({distinct_mb:.0} MB decoded, {:.1}x the cache), {} evicted; {:.1} MB read",
        100.0 * frames_over_bound as f64 / frames as f64,
        flight.worst_factor,
        flight.tiles_loaded,
        flight.distinct_tiles,
        distinct_mb / f64::from(args.cache_mb),
        flight.tiles_evicted,
        flight.bytes_read as f64 / 1e6,
    );
    if signals.requested() {
        return Err(
            Interrupted::by(&signals, format!("{frames} of {} frames flown, reported above", args.frames)).into()
        );
    }
    if let Some(failure) = &streamer.first_failure {
        let what = match flight.tiles_failed {
            0 => format!("tiles could not be read ({failure})"),
            n => format!("{n} tile reads failed (first: {failure})"),
        };
        return Err(Degraded(format!("{what}; frames were drawn without their data")).into());
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::along_line;

    /// The flight turns at both ends: every position lies on the line, it moves no
    /// faster than the distance flown (no jump at a turn), and heads back after each end.
    #[test]
    fn a_flight_turns_at_the_ends_of_its_line() {
        let length = 1000.0;
        let step = 7.3;
        let mut last = along_line(0.0, length);
        assert_eq!(last, (0.0, 1.0));
        for i in 1..2000 {
            let d = f64::from(i) * step;
            let (at, way) = along_line(d, length);
            assert!((0.0..=length).contains(&at), "{d}: {at}");
            assert!((at - last.0).abs() <= step + 1e-9, "{d}: jumped from {} to {at}", last.0);
            // Out on the first pass, back on the second, out again on the third.
            let pass = (d / length).floor() as i64;
            assert_eq!(way, if pass % 2 == 0 { 1.0 } else { -1.0 }, "{d}");
            last = (at, way);
        }
        assert_eq!(along_line(1500.0, length), (500.0, -1.0));
        assert_eq!(along_line(2500.0, length), (500.0, 1.0));
    }
}
