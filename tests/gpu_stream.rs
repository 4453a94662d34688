//! Streamed frames on the GPU (SPEC section 8), under validation: the atlas holds each
//! tile's heights exactly, the vertex shader places every streamed vertex where the
//! plain-Rust placement does (bit for bit, relative to the anchor sample), a layer is
//! reused only once the frames that drew from it completed, and a frame draws terrain.

mod common;

use common::{cli, TempDir};
use glam::DVec3;
use std::sync::Arc;
use vkterrain::app::bench::image_difference;
use vkterrain::draw::lighting_gpu::OwnLighting;
use vkterrain::draw::streamed::{FrameView, HeightRange, StreamedRenderer};
use vkterrain::errors::atlas::HeightAtlas;
use vkterrain::input::archive::Archive;
use vkterrain::lod::block::block_vertex;
use vkterrain::lod::heightfield::Heightfield;
use vkterrain::stream::cache::TileData;
use vkterrain::stream::draw::{self, Resident, StreamedBlock};
use vkterrain::stream::streamer::{Streamer, TileGate};
use vkterrain::stream::traverse::{Selection, View};
use vkterrain::stream::Grid;
use vkterrain::vk::Device;

fn settled(s: &mut Streamer, view: &View) -> Selection {
    for _ in 0..16 {
        let sel = s.frame(view, None, 1.0, 1.0);
        if sel.within_bound() {
            return sel;
        }
        s.settle();
    }
    panic!("not settled");
}

fn views() -> Vec<View> {
    vec![
        View::look_at(DVec3::new(1500.0, 170.0, 2500.0), DVec3::new(2600.0, 60.0, 3800.0), 45.0, 320, 240, 1.0),
        View::look_at(DVec3::new(-400.0, 300.0, -300.0), DVec3::new(1500.0, 0.0, 2500.0), 45.0, 320, 240, 1.0),
        View::look_at(DVec3::new(2100.0, 900.0, 1666.0), DVec3::new(2150.0, 0.0, 1700.0), 60.0, 320, 240, 1.0),
    ]
}

/// The tiles `sel` draws from, as the cache holds them.
fn tiles(s: &Streamer, sel: &Selection) -> Vec<Arc<TileData>> {
    sel.used.iter().map(|k| s.cache.peek(*k).expect("used tiles are held").clone()).collect()
}

/// Where the shader must put every vertex: the CPU placement from the held tiles, in
/// f32 the way the shader computes it (integer sample minus anchor, then times spacing).
fn expected(grid: &Grid, s: &Streamer, anchor: [i64; 2], blocks: &[StreamedBlock]) -> Vec<[f32; 3]> {
    let layout = draw::layout(grid);
    let resident = Resident { grid, cache: &s.cache };
    let k = layout.k();
    let mut out = Vec::new();
    for b in blocks {
        for v in 0..k {
            for u in 0..k {
                let (x, z, raw) = block_vertex(&resident, &layout, &b.block, u, v);
                assert!(!raw.is_nan(), "{:?} vertex ({u}, {v}) has a held sample", b.block);
                out.push([
                    (x - anchor[0]) as f32 * grid.spacing[0] as f32,
                    raw * grid.height_scale as f32,
                    (z - anchor[1]) as f32 * grid.spacing[1] as f32,
                ]);
            }
        }
    }
    out
}

/// The rough field in whole units (a 16-bit archive, an R16_UNORM atlas), scaled back.
fn rough16() -> Heightfield {
    let f = common::rough();
    common::field16(f.width, f.height, [3.0, 5.0], 0.25, |x, z| (f.raw_at(x as i64, z as i64) * 4.0 + 100.0) as u16)
}

#[test]
fn streamed_vertices_from_the_atlas_are_the_cpu_placement_and_a_frame_draws_terrain() {
    for (hf, unorm16) in [(common::rough(), false), (rough16(), true)] {
        streamed_frames_match(&hf, unorm16);
    }
}

fn streamed_frames_match(hf: &Heightfield, unorm16: bool) {
    let dir = TempDir::new("gpu-stream");
    let archive = common::archive_of(hf, &dir);
    let grid = Grid::from_meta(&archive.meta);
    let device = common::gpu();
    {
        let mut s = Streamer::new(archive, grid, 1 << 30);
        let atlas = HeightAtlas::new(&device, &grid, 64 << 20).unwrap();
        assert_eq!(atlas.unorm16(), unorm16, "the atlas format follows the archive's samples");
        // Tiles read reach the cache through the atlas's thread: every held tile is drawable.
        s.attach(Box::new(atlas.feed()), HeightAtlas::cache_tiles(atlas.layer_count()));
        let lit = OwnLighting::everything_lit(&device).unwrap();
        let mut renderer = StreamedRenderer::new(&device, draw::layout(&grid), 320, 240).unwrap();
        let (mut compared, mut mutated, mut morphed) = (0usize, 0usize, 0usize);
        for (i, view) in views().iter().enumerate() {
            let sel = settled(&mut s, view);
            let blocks = draw::stitched_blocks(&grid, &s.cache, &sel);
            // Morphed vertices too: the parent's surface from the atlas as on the CPU.
            morphed += blocks.iter().filter(|b| b.block.morph < vkterrain::lod::block::MORPH_ONE).count();
            assert!(sel.used.iter().all(|k| atlas.holds(*k)), "pose {i}: a used tile is not drawable");
            let fv = frame_view(&grid, view, &lit);
            let anchor = fv.anchor;
            let want = expected(&grid, &s, anchor, &blocks);
            let got = renderer.capture(&atlas, &fv, &blocks).unwrap();
            assert_eq!(got.len(), want.len(), "pose {i}");
            for (j, (g, w)) in got.iter().zip(&want).enumerate() {
                assert_eq!([g[0], g[1], g[2]], *w, "pose {i}: block {:?} vertex {}", blocks[j / 1089].block, j % 1089);
            }
            compared += got.len();

            // A block drawn from another tile's layer is caught: the check can fail.
            // (Another tile covering the block holds the same samples: pick one that does not.)
            let layout = draw::layout(&grid);
            let covers = |t: vkterrain::stream::TileKey, b: &vkterrain::lod::block::DrawBlock| {
                let span = grid.tile_span(t.level) as u32;
                let (ox, oz) = b.origin(&layout);
                (ox / span, oz / span) == (t.tx, t.tz)
            };
            if let Some(j) = (1..blocks.len()).find(|&j| !covers(blocks[j].tile, &blocks[0].block)) {
                let mut wrong = blocks.clone();
                wrong[0].tile = blocks[j].tile;
                let bad = renderer.capture(&atlas, &fv, &wrong).unwrap();
                let differs = (0..1089).any(|v| [bad[v][0], bad[v][1], bad[v][2]] != want[v]);
                assert!(
                    differs,
                    "pose {i}: the wrong tile's heights went unnoticed: {:?} from {:?}",
                    blocks[0], blocks[j].tile
                );
                mutated += 1;
            }

            let (pixels, stats) = renderer.render(&atlas, &fv, &blocks).unwrap();
            assert_eq!((stats.blocks, stats.missing), (blocks.len(), 0));
            let sky = pixels.chunks(4).filter(|p| p[..3] == pixels[..3]).count();
            let terrain = pixels.len() / 4 - sky;
            assert!(terrain > pixels.len() / 4 / 5, "pose {i}: {terrain} terrain pixels of {}", pixels.len() / 4);
        }
        assert!(compared > 100_000, "vertices compared: {compared}");
        assert!(morphed > 20, "morphing blocks compared: {morphed}");
        assert!(mutated >= 2, "the wrong-tile check ran at {mutated} poses");
    }
    common::finish(device);
}

/// A frame seen from `view`, its ramp over 0 to 1000 m, no fog.
fn frame_view<'a>(grid: &'a Grid, view: &View, lighting: &'a OwnLighting) -> FrameView<'a> {
    let (anchor, cam) = view.relative(grid);
    let heights = HeightRange { world: [0.0, 1000.0], absolute: false };
    let light = glam::Vec3::Y;
    FrameView {
        grid,
        anchor,
        cam,
        heights,
        fog: 0.0,
        light,
        lighting,
        colour_by_lod: false,
        wireframe: false,
        background: None,
    }
}

/// The atlas's thread rewrites a layer only when the host cache has let its tile go and
/// every frame that drew from it has completed (the draw queue's timeline): two layers,
/// two tiles drawn by frame 1, two more tiles sent. Refused while the cache holds the
/// tiles, refused while frame 1 is not complete, taken once it is.
#[test]
fn an_atlas_layer_is_reused_only_after_the_frames_that_drew_it() {
    let dir = TempDir::new("gpu-stream-reuse");
    let hf = common::rough();
    let archive = common::archive_of(&hf, &dir);
    let grid = Grid::from_meta(&archive.meta);
    let device = common::gpu();
    {
        let mut s = Streamer::new(archive, grid, 1 << 30);
        let view = views()[0];
        let sel = settled(&mut s, &view);
        let held = tiles(&s, &sel);
        assert!(held.len() >= 4);
        // Room for two tiles (heights and deviations).
        let atlas = HeightAtlas::new(&device, &grid, 2 * HeightAtlas::layer_bytes(&grid)).unwrap();
        assert_eq!(atlas.layer_count(), 2);
        let feed = atlas.feed();
        let pass = |tiles: &[Arc<TileData>]| {
            feed.send(tiles.iter().map(|t| (t.clone(), 0)).collect());
            feed.wait();
            let (back, refused) = feed.take();
            (back.len(), refused.len())
        };
        let (first, next) = (&held[..2], &held[2..4]);
        assert_eq!(pass(first), (2, 0));
        // Frame 1 draws both (recorded; its submission comes later).
        let (layers, generation) = atlas.draw_layers(first.iter().map(|t| t.key), 1);
        assert!(layers.iter().all(Option::is_some) && generation == 1, "{layers:?} {generation}");
        // Frame 1 has not completed, and the cache still holds both: nothing is rewritten.
        assert_eq!(pass(next), (0, 2));
        feed.release(first.iter().map(|t| t.key).collect());
        assert_eq!(pass(next), (0, 2), "let go, but frame 1 has not completed");
        assert!(first.iter().all(|t| atlas.holds(t.key)));
        // Frame 1 completes (an empty frame signals it on the draw queue's timeline).
        let lit = OwnLighting::everything_lit(&device).unwrap();
        let mut renderer = StreamedRenderer::new(&device, draw::layout(&grid), 64, 48).unwrap();
        let fv = frame_view(&grid, &view, &lit);
        renderer.render_unread(&atlas, &fv, &[]).unwrap();
        // The frame's fence has signalled; the atlas's thread reads the frame timeline,
        // which lavapipe may update a moment later (seen once on a loaded machine): wait
        // for the value itself.
        let (sems, values) = ([atlas.frames()], [1u64]);
        let info = ash::vk::SemaphoreWaitInfo::default().semaphores(&sems).values(&values);
        // SAFETY: the atlas's semaphore is live; the arrays outlive the call.
        unsafe { device.raw.wait_semaphores(&info, 10_000_000_000) }.expect("frame 1 completes");
        assert_eq!(pass(next), (2, 0));
        assert!(next.iter().all(|t| atlas.holds(t.key)) && !first.iter().any(|t| atlas.holds(t.key)));
        assert_eq!(atlas.uploaded().tiles, 4);
        assert_eq!(atlas.uploaded().dropped, 4);
        assert!(atlas.failure().is_none());
        // A tile sent again while its layer still holds it comes back without a copy.
        feed.release(next[..1].iter().map(|t| t.key).collect());
        assert_eq!(pass(&next[..1]), (1, 0));
        assert_eq!(atlas.uploaded().tiles, 4);
        // A tile let go, its layer reused, then read again into another layer is held
        // by the cache from then on: its new layer is not rewritten for a later tile.
        let (a, b, c, d) = (&next[0], &next[1], &first[0], &first[1]);
        feed.release(vec![a.key]);
        assert_eq!(pass(std::slice::from_ref(c)), (1, 0), "a's layer takes c");
        feed.release(vec![b.key]);
        assert_eq!(pass(std::slice::from_ref(a)), (1, 0), "a comes back into b's layer");
        assert_eq!(pass(std::slice::from_ref(d)), (0, 1), "a and c are held: d finds no layer");
        assert!(atlas.holds(a.key) && atlas.holds(c.key) && !atlas.holds(d.key));
        // A budget below one tile is refused with the figure.
        let err = HeightAtlas::new(&device, &grid, 1000).err().expect("no layer fits").to_string();
        assert!(err.contains("--gpu-mb") && err.contains("bytes a tile"), "{err}");
    }
    common::finish(device);
}

/// `vkterrain stream --gpu-mb` end to end under validation: every frame of the flight is
/// drawn from the atlas, no block misses its layer, the last frame shows terrain, and no
/// validation message is reported. An atlas too small for the frames' tiles limits what
/// the host cache holds: frames are drawn coarser and counted over the bound, no block
/// goes missing.
#[test]
fn the_stream_command_draws_every_frame_from_the_atlas_under_validation() {
    let dir = TempDir::new("gpu-stream-cli");
    let archive = dir.path().join("s.pmtiles");
    let a = archive.to_str().unwrap();
    let o = cli(&["prepare", "--synthetic", "1025", "--out", a]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let png = dir.path().join("last.png");
    let fly = |gpu_mb: &str, out: Option<&str>| {
        let mut args = vec![
            "stream",
            a,
            "--frames",
            "24",
            "--fps",
            "240",
            "--speed",
            "4000",
            "--size",
            "256x192",
            "--validation",
            "on",
        ];
        args.extend(["--gpu-mb", gpu_mb]);
        if let Some(out) = out {
            args.extend(["--out", out]);
        }
        let o = cli(&args);
        assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
        serde_json::from_slice::<serde_json::Value>(&o.stdout).unwrap()
    };
    let r = fly("32", Some(png.to_str().unwrap()));
    let gpu = &r["gpu"];
    assert_eq!(gpu["frames_drawn"], 24, "{r}");
    assert_eq!(gpu["frames_missing_blocks"], 0, "{r}");
    assert_eq!(gpu["validation"], true, "{r}");
    assert_eq!(gpu["validation_messages"], 0, "{r}");
    // No `--sun` here: the default sun's shadows, as the other commands draw them.
    assert_eq!(gpu["lighting"]["shadows"], true, "{r}");
    assert!(gpu["tiles_uploaded"].as_u64().unwrap() > 0, "{r}");
    let img = image::open(&png).unwrap().to_rgba8();
    assert_eq!(img.dimensions(), (256, 192));
    let terrain = common::terrain_pixels(&img);
    assert!(terrain > 256 * 192 / 5, "{terrain} terrain pixels");
    // Room for five 16-bit tiles (259^2 samples with their border, and half of a slot of
    // 256^2 half-float deviations each): fewer than the frames want. The host cache then
    // holds at most four tiles, so every block drawn finds its layer, and the frames that
    // wanted more are counted over the bound (without that limit, blocks go missing from
    // the picture unreported).
    let r = fly("1", None);
    assert_eq!(r["gpu"]["atlas_layers"], 5, "{r}");
    assert_eq!(r["gpu"]["frames_missing_blocks"], 0, "{r}");
    assert!(r["frames_over_bound"].as_u64().unwrap() > 0, "{r}");
    assert_eq!(r["gpu"]["validation_messages"], 0, "{r}");
}

/// `render --stream` draws an archive through the streaming path under validation: the
/// frame waits for its tiles and is within the bound, every block finds its layer, the
/// picture shows terrain. A cache too small for the view is reported over the bound, not
/// hidden; options the streamed path cannot honour are refused by name (exit 2).
#[test]
fn render_draws_an_archive_streamed_within_the_bound() {
    let dir = TempDir::new("gpu-stream-render");
    let archive = dir.path().join("s.pmtiles");
    let a = archive.to_str().unwrap();
    let o = cli(&["prepare", "--synthetic", "1025", "--out", a]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let png = dir.path().join("r.png");
    let p = png.to_str().unwrap();
    let render = |extra: &[&str]| {
        let mut args = vec!["render", "--heightmap", a, "--stream", "--validation", "on", "--size", "320x240"];
        args.extend(["--camera", "1500,900,16000", "--look-at", "15000,300,15000", "--out", p]);
        args.extend(extra);
        cli(&args)
    };
    let o = render(&[]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let r: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    assert_eq!((r["streamed"].as_bool(), r["within_bound"].as_bool()), (Some(true), Some(true)), "{r}");
    assert_eq!(r["gpu"]["frames_missing_blocks"], 0, "{r}");
    assert_eq!(r["gpu"]["validation_messages"], 0, "{r}");
    assert!(r["blocks"].as_u64().unwrap() > 10, "{r}");
    // The blocks' errors came from the errors activity's generation over the atlas.
    assert!(r["blocks_bounded_by_errors"].as_u64().unwrap() > 10, "{r}");
    assert_eq!(r["blocks_bounded_by_tiles"], 0, "{r}");
    assert!(r["gpu"]["errors"]["generations"].as_u64().unwrap() >= 1, "{r}");
    // `errors` over the same tiles: generations over the atlas and their cost.
    let o = cli(&["errors", a, "--stream", "--repeat", "2", "--validation", "on", "--size", "320x240"]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let e: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    assert_eq!((e["streamed"].as_bool(), e["validation_messages"].as_u64()), (Some(true), Some(0)), "{e}");
    assert!(e["tiles_shaded"].as_u64().unwrap() > 0 && e["readback_bytes"].as_u64().unwrap() > 0, "{e}");
    assert!(e["generations"] == 2 && e["update_ms"].as_f64().unwrap() > 0.0, "{e}");
    // The grid the blocks cover and its roots, as in memory (a review found the samples
    // reported as the grid, and no roots).
    assert_eq!((&e["grid"], &e["roots"]), (&serde_json::json!([1025, 1025]), &serde_json::json!([1, 1])), "{e}");
    // Only the cells shaded are read back: 8 x 8 blocks of 4 bytes a tile.
    assert_eq!(e["readback_bytes"].as_u64(), e["tiles_shaded"].as_u64().map(|t| t * 256), "{e}");
    // `--dump` in the in-memory layout: a value for every block of a tile shaded.
    let dump = dir.path().join("e.f32");
    let o = cli(&["errors", a, "--stream", "--dump", dump.to_str().unwrap(), "--validation", "on"]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let floats = std::fs::read(&dump).unwrap().len() / 4;
    assert_eq!(floats, (1..=5).map(|j| 1 << (2 * (5 - j))).sum::<usize>(), "LODs 1 to 5 of a 1025^2 archive");
    // Shadows from a lighting map of the terrain's own size, made from the finest tiles.
    let lighting = &r["gpu"]["lighting"];
    assert_eq!(
        (lighting["shadows"].as_bool(), lighting["texels"].clone()),
        (Some(true), serde_json::json!([1025, 1025]))
    );
    assert_eq!(
        (lighting["samples_per_texel"].as_u64(), lighting["heights_samples_apart"].as_u64()),
        (Some(1), Some(1))
    );
    // The morph terms spread over three threads: the same frame, byte for byte.
    let one_thread = std::fs::read(&png).unwrap();
    let o = render(&["--traversal-threads", "3"]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let threaded: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    assert_eq!((r["traversal_threads"].as_u64(), threaded["traversal_threads"].as_u64()), (Some(1), Some(3)));
    assert_eq!(r["shading"], "gradient-map", "{r}");
    assert!(threaded["morphing"].as_u64().unwrap() > 0, "{threaded}");
    assert_eq!((&threaded["morphing"], &threaded["blocks"]), (&r["morphing"], &r["blocks"]), "{threaded}");
    assert!(std::fs::read(&png).unwrap() == one_thread, "three threads drew another frame");
    // The fields docs/commands.md names: the streamer's `stats`, which count every tile
    // the frame read (the top tiles too: each one uploaded was read first), and the block
    // grid as in memory (1025^2: one root of 2^10 + 1 samples).
    let (loaded, uploaded) =
        (r["stats"]["tiles_loaded"].as_u64().unwrap(), r["gpu"]["tiles_uploaded"].as_u64().unwrap());
    assert!(uploaded > 0 && loaded >= uploaded, "{loaded} tiles read, {uploaded} uploaded: {r}");
    assert!(r["frames_to_settle"].as_u64().unwrap() >= 1, "{r}");
    assert_eq!(
        (r["grid"].clone(), r["roots"].clone()),
        (serde_json::json!([1025, 1025]), serde_json::json!([1, 1])),
        "{r}"
    );
    let img = image::open(&png).unwrap().to_rgba8();
    let terrain = common::terrain_pixels(&img);
    assert!(terrain > 320 * 240 / 3, "{terrain} terrain pixels");

    // `--audit` measures the streamed frame as drawn against every sample (the archive
    // in memory): within delta, every visible sample covered.
    let o = render(&["--audit"]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let r: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    let audited = r["max_audited_error_px"].as_f64().unwrap();
    println!("render --stream --audit: {audited:.3} px over {} samples", r["audited_samples"]);
    assert_eq!((r["audit_within_delta"].as_bool(), r["uncovered_samples"].as_u64()), (Some(true), Some(0)), "{r}");
    assert!(audited > 0.3 && r["audited_samples"].as_u64().unwrap() > 100_000, "{r}");

    // One MB holds the top tiles and little more: the frame is drawn, over the bound, and
    // the audit says by how much.
    let o = render(&["--cache-mb", "1", "--audit"]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let over: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    println!("--cache-mb 1: audited {} px", over["max_audited_error_px"]);
    assert_eq!(over["audit_within_delta"], false, "{over}");
    assert_eq!(over["uncovered_samples"], 0, "{over}");
    let r: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    assert_eq!(r["within_bound"], false, "{r}");
    assert!(r["blocks_over_bound"].as_u64().unwrap() > 0 && r["worst_factor"].as_f64().unwrap() > 1.0, "{r}");
    assert!(String::from_utf8_lossy(&o.stderr).contains("over the bound"));

    // `--lod full`: every block at LOD 0, so the frame as drawn is every sample (audited
    // at 0 px), with more triangles than the bound's.
    let o = render(&["--lod", "full", "--audit"]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let full: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    assert_eq!(
        (full["lod"].as_str(), full["within_bound"].as_bool(), full["morphing"].as_u64()),
        (Some("full"), Some(true), Some(0)),
        "{full}"
    );
    assert!(full["max_audited_error_px"].as_f64().unwrap() < 1e-3 && full["uncovered_samples"] == 0, "{full}");
    assert!(full["triangles"].as_u64().unwrap() > 2 * r["triangles"].as_u64().unwrap(), "{full} against {r}");
    let o = render(&["--lod", "distance"]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let rings: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    assert_eq!(
        (rings["lod"].as_str(), rings["gpu"]["validation_messages"].as_u64()),
        (Some("distance"), Some(0)),
        "{rings}"
    );
    assert!(rings["triangles"].as_u64().unwrap() < full["triangles"].as_u64().unwrap(), "{rings}");
    // Deferred by default, forward when asked.
    assert_eq!(r["pixels"], "deferred", "{r}");
    let o = render(&["--pixels", "forward"]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let forward: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    assert_eq!((&forward["pixels"], &forward["gpu"]["validation_messages"]), (&"forward".into(), &0.into()));
    // The paper's error mode: its blocks chosen by the errors activity's estimate,
    // fewer than the bound's (a per-vertex estimate, not a bound).
    let strict: serde_json::Value = serde_json::from_slice(&render(&[]).stdout).unwrap();
    let o = render(&["--error-mode", "paper"]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let paper: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    assert_eq!((paper["error_mode"].as_str(), paper["validation_messages"].as_u64()), (Some("paper"), Some(0)));
    assert!(paper["blocks_bounded_by_errors"].as_u64().unwrap() > 10, "{paper}");
    let fewer = paper["blocks"].as_u64().unwrap() < strict["blocks"].as_u64().unwrap();
    assert!(fewer, "{paper} against {strict}");
    // High above, only blocks coarser than the top tile's level are drawn: their paper
    // errors come from the top tile's generation too (a review found the frame settled
    // on the summaries' bound before any generation).
    let mut args = vec!["render", a, "--stream", "--validation", "on", "--size", "320x240", "--error-mode", "paper"];
    args.extend(["--camera", "15000,150000,15000", "--look-at", "15000,0,15001", "--out", p]);
    let o = cli(&args);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let high: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    assert!(high["errors_generation"].as_u64().unwrap() > 0, "{high}");
    assert_eq!(high["blocks_bounded_by_errors"], high["blocks"], "{high}");
    // Free pacing (two generations may be in flight) draws the same frame.
    let o = render(&["--error-pacing", "free"]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let free: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    assert_eq!((&free["blocks"], &free["triangles"]), (&strict["blocks"], &strict["triangles"]), "{free}");
    assert_eq!(free["validation_messages"], 0, "{free}");
    // Ray-cast blocks over tiles, reported as in memory.
    let o = render(&["--raycast", "all", "--morph", "off"]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let cast: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    assert_eq!((&cast["raycast"], &cast["validation_messages"]), (&serde_json::json!("all"), &serde_json::json!(0)));
    assert!(cast["raycast_blocks"].as_u64().is_some(), "{cast}");
    // Occlusion culling as in memory: on by default, off when asked (its report null).
    assert!(r["occlusion"]["tested"].as_u64().is_some_and(|t| t > 0), "{r}");
    let o = render(&["--occlusion", "off"]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let off: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    assert!(off["occlusion"].is_null(), "{off}");
    let o = render(&["--occlusion", "on"]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    // The errors activity's refresh and share of the wall time apply to tiles too.
    let o = render(&["--refresh-at", "0.2", "--update-share", "0.5", "--error-pacing", "paced"]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    // Without a terrain: the built-in one, cut into tiles.
    let o = cli(&["render", "--stream", "--size", "64x48", "--validation", "on", "--out", p]);
    assert!(o.status.success(), "--stream on the built-in terrain: {}", String::from_utf8_lossy(&o.stderr));
    let r: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    assert_eq!((r["streamed"].clone(), r["validation_messages"].clone()), (true.into(), 0.into()), "{r}");

    // An atlas of five layers: the cache holds no more tiles than that, so the frame is
    // drawn coarser and over the bound, with no block missing from the picture.
    let o = render(&["--gpu-mb", "1"]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let r: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    assert_eq!((r["within_bound"].as_bool(), r["blocks_missing_a_layer"].as_bool()), (Some(false), Some(false)), "{r}");
    assert_eq!(r["gpu"]["frames_missing_blocks"], 0, "{r}");
    // The archive's own scale gives way to the options, and says so.
    let o = render(&["--spacing", "10", "--height-scale", "2"]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let r: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    assert_eq!(
        (r["spacing_m"].clone(), r["height_scale_m"].clone()),
        (serde_json::json!([10.0, 10.0]), serde_json::json!(2.0))
    );
    assert!(String::from_utf8_lossy(&o.stderr).contains("from --spacing"));
    // A terrain file is cut into tiles in memory (nothing written) and drawn streamed: the
    // same frame as its archive prepared beforehand, byte for byte.
    let ps = common::data("puget_sound/ps_height_1k.png");
    let pre = dir.path().join("ps.pmtiles");
    let o = cli(&["prepare", ps.to_str().unwrap(), "--out", pre.to_str().unwrap()]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let ps_view = ["--stream", "--size", "160x120", "--camera", "20000,9000,150000", "--look-at", "80000,0,80000"];
    let frame = |heightmap: &std::path::Path, out: &std::path::Path| {
        let mut args = vec!["render", "--heightmap", heightmap.to_str().unwrap(), "--out", out.to_str().unwrap()];
        args.extend(ps_view);
        let o = cli(&args);
        assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
        let r: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
        assert_eq!(r["within_bound"], true, "{r}");
        std::fs::read(out).unwrap()
    };
    let on_the_fly = frame(&ps, &dir.path().join("fly.png"));
    assert_eq!(on_the_fly, frame(&pre, &dir.path().join("pre.png")), "the same frame from either");
    // A raw file streamed: prepared on the fly with --raw-size and --spacing (as the
    // loader reads it; no spacing assumed), drawn at that spacing. An archive knows its
    // own size: --raw-size with one is refused, naming it.
    let raw = dir.path().join("t.f32");
    let samples: Vec<u8> =
        (0..300 * 200).flat_map(|i| (((i % 300 + i / 300) % 37) as f32 * 3.0).to_le_bytes()).collect();
    std::fs::write(&raw, samples).unwrap();
    let mut args = vec!["render", "--heightmap", raw.to_str().unwrap(), "--raw-size", "300x200", "--spacing", "10"];
    args.extend(["--stream", "--size", "64x48", "--out", p]);
    let o = cli(&args);
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(o.status.success(), "{err}");
    let r: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    assert_eq!(r["spacing_m"], serde_json::json!([10.0, 10.0]), "{r}");
    assert!(!err.contains("ASSUMED; give --spacing"), "{err}");
    let o = render(&["--raw-size", "300x200"]);
    let err = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(2), "{err}");
    assert!(err.contains("--raw-size") && err.contains("s.pmtiles"), "{err}");
    // A viewport larger than an image, and an archive whose top tiles are cut off: exit
    // 2, one line naming the problem.
    let o = render(&["--size", "20000x100"]);
    assert_eq!(o.status.code(), Some(2), "{}", String::from_utf8_lossy(&o.stderr));
    // The finest tiles (the lighting map's here) cut off, the top ones whole (the archive
    // stores the coarsest first): the frame is drawn without shadows, with a warning
    // naming the file and the tile, not refused; it finished degraded (exit 3).
    let bytes = std::fs::read(&archive).unwrap();
    let half = dir.path().join("half.pmtiles");
    std::fs::write(&half, &bytes[..bytes.len() * 2 / 3]).unwrap();
    // RUST_LOG unset, as a user runs it (the tests' runner asks for errors only).
    let half_path = half.to_str().unwrap();
    let args = ["render", "--heightmap", half_path, "--stream", "--validation", "on", "--size", "64x48", "--out", p];
    let o = common::run_bounded_logging(&args.map(String::from), 300, None);
    let err = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(3), "{err}");
    let warning = err.lines().find(|l| l.contains("without shadows")).unwrap_or_else(|| panic!("no warning: {err}"));
    assert!(
        warning.starts_with("vkterrain: warning: ") && warning.contains("half.pmtiles") && warning.contains("tile"),
        "{warning}"
    );
    let r: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    assert_eq!(r["gpu"]["lighting"]["shadows"], false, "{r}");
    assert_eq!(r["gpu"]["validation_messages"], 0, "{r}");
    assert!(r["gpu"]["lighting"]["unreadable"].as_str().is_some_and(|w| w.contains("half.pmtiles")), "{r}");
    assert_eq!(r["degraded"], true, "{r}");
    let cut = dir.path().join("cut.pmtiles");
    std::fs::write(&cut, &bytes[..2000]).unwrap();
    let o = cli(&["render", "--heightmap", cut.to_str().unwrap(), "--stream", "--size", "64x64", "--out", p]);
    let err = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(2), "{err}");
    assert!(err.contains("top tiles") && err.contains("cut.pmtiles"), "{err}");
}

/// A streamed frame is coloured as the same terrain in memory: at the default view (the
/// same camera, from the archive's recorded height range, not its top tiles' coarser
/// one), at a low view towards the horizon and from under the surface, with the same
/// ramp, snow line, sea level, light, shadows, sky and culled underside, the frames differ
/// only by the streamed path's own selection (RMSE 1.39 at the default view; 3.91 when
/// streamed frames were shaded forward with flat normals), and both show the Sound's
/// water.
/// Before the range, the water and the sky were shared (the top tiles' range: the peaks'
/// snow twice as wide; no water; a flat sky): RMSE 21.3 at the default view (another
/// camera), 17.1 at the low one; before the underside was culled, 77 from under it.
/// `--sun` turns the light and its shadows as in memory: lit from 120,30, RMSE 1.68 with
/// the lighting map (4.84 shaded forward, flat), 6.85 without it (build 30da1bd,
/// streamed frames without shadows).
#[test]
fn a_streamed_frame_is_coloured_as_the_terrain_in_memory() {
    let dir = TempDir::new("gpu-stream-colours");
    let archive = dir.path().join("ps.pmtiles");
    let a = archive.to_str().unwrap();
    let ps = common::data("puget_sound/ps_height_1k.png");
    let o = cli(&["prepare", ps.to_str().unwrap(), "--out", a]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let frame = |extra: &[&str], name: &str| {
        let out = dir.path().join(name);
        let mut args = vec!["render", "--heightmap", a, "--validation", "on", "--size", "320x180"];
        args.extend(["--out", out.to_str().unwrap()]);
        args.extend(extra);
        let o = cli(&args);
        assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
        let r: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
        let messages = if r["streamed"] == true { &r["gpu"]["validation_messages"] } else { &r["validation_messages"] };
        assert_eq!(messages, 0, "{r}");
        (r["camera"].clone(), image::open(&out).unwrap().to_rgba8())
    };
    // Water: clearly bluer than green and red (the ramp has no such colour).
    let water = |img: &image::RgbaImage| {
        img.pixels()
            .filter(|p| i32::from(p[2]) > i32::from(p[1]) + 15 && i32::from(p[2]) > i32::from(p[0]) + 40)
            .count()
    };
    let rmse = |a: &image::RgbaImage, b: &image::RgbaImage| image_difference(a.as_raw(), b.as_raw());
    let low = ["--camera", "30000,900,30000", "--look-at", "90000,0,90000"];
    // Under the surface both paths see the sky through the terrain's culled underside,
    // and the hillsides that face the camera from below (slivers: larger differences).
    let under = ["--camera", "80000,-2000,80000", "--look-at", "90000,500,90000"];
    // `--background`: a plain colour where the sky was, as in memory (a frame that kept
    // the sky differs from memory's over the whole sky).
    let plain = ["--background", "0.3,0.1,0.1"];
    // The paper's texture stretched over the terrain, and a detail texture over it, as in
    // memory, without morphing: the two paths choose different morph factors (the same
    // textured view morphed differs by RMSE 3.48, 1.38 % of the pixels over 16 levels;
    // in memory alone, morph on against off by 4.13), and the texture's detail turns a
    // fraction of a pixel's shift into another colour. Unmorphed: RMSE 0.02 textured,
    // 1.41 with a detail texture four times across (reconstructed from depth, the point's
    // sample coordinates differ in their last bits).
    let texture = common::data("puget_sound/ps_texture_1k.png");
    let t = texture.to_str().unwrap();
    let textured = ["--texture", t, "--morph", "off"];
    let detail = ["--texture", t, "--detail", t, "--detail-tiling", "4", "--detail-weight", "0.5", "--morph", "off"];
    let detailed = [&low[..], &detail[..]].concat();
    let views: [(&str, &[&str], f64, f64, bool); 6] = [
        ("default view", &[], 2.5, 0.005, true),
        ("plain background", &plain, 2.5, 0.005, true),
        ("low view", &low, 2.5, 0.005, true),
        ("under", &under, 7.0, 0.01, false),
        ("textured", &textured, 0.5, 0.001, false),
        ("textured with detail", &detailed, 2.0, 0.005, false),
    ];
    for (view, extra, most_rmse, most_far, water_seen) in views {
        let (cam_mem, mem) = frame(extra, "mem.png");
        let (cam_str, streamed) = frame(&[extra, &["--stream"]].concat(), "str.png");
        assert_eq!(cam_str, cam_mem, "{view}: the same camera");
        let (e, far_share) = rmse(&mem, &streamed);
        println!(
            "{view}: streamed against in memory: RMSE {e:.2}, {:.2} % of pixels over 16 levels",
            100.0 * far_share
        );
        assert!(
            e < most_rmse && far_share < most_far,
            "{view}: RMSE {e:.2}, {:.2} % over 16 levels",
            100.0 * far_share
        );
        if water_seen {
            let (wm, ws) = (water(&mem), water(&streamed));
            assert!(wm > 200 && ws * 5 > wm * 2, "{view}: water pixels: {wm} in memory, {ws} streamed");
        }
    }
    // The textures are drawn: far from the untextured streamed frame, and the detail from
    // the base alone.
    let plain_frame = frame(&["--stream"], "plain.png").1;
    let textured_frame = frame(&[&textured[..], &["--stream"]].concat(), "tex.png").1;
    let detailed_frame = frame(&[&detailed[..], &["--stream"]].concat(), "detail.png").1;
    let base_frame = frame(&[&low[..], &textured[..], &["--stream"]].concat(), "base.png").1;
    let (apart, _) = rmse(&plain_frame, &textured_frame);
    let (detail_apart, _) = rmse(&base_frame, &detailed_frame);
    println!("textured against untextured: RMSE {apart:.2}; with detail against without: {detail_apart:.2}");
    assert!(apart > 10.0 && detail_apart > 3.0, "textures not drawn: RMSE {apart:.2}, detail {detail_apart:.2}");
    // `--sun` sets the light's direction and its shadows: the streamed frame lit from the
    // east-south-east is nearer the in-memory one than the streamed frame lit from the
    // default direction, and nearer than it was without shadows (6.85).
    let sun = ["--sun", "120,30"];
    let (_, mem) = frame(&sun, "mem.png");
    let (_, streamed) = frame(&[&sun[..], &["--stream"]].concat(), "str.png");
    let (_, default_sun) = frame(&["--stream"], "str-default.png");
    let ((lit, _), (unlit, _)) = (rmse(&mem, &streamed), rmse(&mem, &default_sun));
    println!("--sun 120,30: RMSE {lit:.2} lit from there, {unlit:.2} from the default direction");
    assert!(lit < 2.5 && lit * 1.5 < unlit, "--sun 120,30: RMSE {lit:.2}, from the default direction {unlit:.2}");
    // With the same selection (every block at full resolution: `--lod full`) the
    // streamed frame is the in-memory one up to rounding, shadows and occlusion included:
    // deferred (the default: the lighting map holds every sample here, and the normals
    // and sea come from them as memory's from its own) RMSE 0.03 lit from 120,15 and 0.02
    // with `--sun off`; forward with the same normals (`--shading heights`) 0.19 and 0.25
    // (4.66 with streamed frames unshadowed, build 30da1bd).
    for (shading, most_rmse, most_far) in [(&[][..], 0.15, 0.0001), (&["--shading", "heights"][..], 0.6, 0.0005)] {
        for sun in ["120,15", "off"] {
            let same = ["--lod", "full", "--sun", sun];
            let (_, m) = frame(&same, "mem.png");
            let (_, s) = frame(&[&same[..], &["--stream"], shading].concat(), "str.png");
            let (e, far) = rmse(&m, &s);
            println!("--lod full --sun {sun} {shading:?}: RMSE {e:.2}, {:.3} % of pixels over 16 levels", 100.0 * far);
            assert!(
                e < most_rmse && far < most_far,
                "--lod full --sun {sun} {shading:?}: RMSE {e:.2}, {:.3} % over 16 levels",
                100.0 * far
            );
        }
    }
    // `--colour-by-lod` tints each block by its LOD with the in-memory palette, and the
    // streamed bound (SPEC 8: each block's 8 x 8 squares, each from its own box) selects
    // the blocks memory's error images select here (43 each): RMSE 3.7 tinted, 34.8
    // untinted (before the squares, 55 blocks against 43: RMSE 18.7).
    let (_, mem_lod) = frame(&["--colour-by-lod"], "mem.png");
    let (_, streamed_lod) = frame(&["--colour-by-lod", "--stream"], "str.png");
    let ((tinted, _), (untinted, _)) = (rmse(&mem_lod, &streamed_lod), rmse(&mem_lod, &default_sun));
    println!("--colour-by-lod: RMSE {tinted:.2} tinted, {untinted:.2} untinted");
    assert!(tinted < 6.0 && tinted * 4.0 < untinted, "--colour-by-lod: RMSE {tinted:.2}, untinted {untinted:.2}");
    // Forward frames (`--pixels forward`) take each point's normal and water from the held
    // samples' gradient map as the deferred pass does, which here holds every sample: as
    // near the in-memory frame as deferred (RMSE 1.39 and 1.68 lit from the east-south-
    // east; each triangle's own normal gave 3.91 and 4.84). `--shading heights` takes
    // them from the heights of each block's tile instead (often coarser than the
    // terrain's samples, interpolated as memory interpolates its own): 3.48 and 4.08.
    let heights = ["--stream", "--shading", "heights"];
    let forward = ["--stream", "--pixels", "forward"];
    let (_, mem_default) = frame(&[], "mem.png");
    let (_, deferred_default) = frame(&["--stream"], "str-deferred.png");
    let (_, flat_default) = frame(&forward, "str-flat.png");
    let (_, flat_sun) = frame(&[&sun[..], &forward[..]].concat(), "str-flat-sun.png");
    let (_, smooth) = frame(&heights, "str-smooth.png");
    let (_, smooth_sun) = frame(&[&sun[..], &heights[..]].concat(), "str-smooth-sun.png");
    let ((flat, flat_far), (smooth, smooth_far)) = (rmse(&mem_default, &flat_default), rmse(&mem_default, &smooth));
    let ((smooth_lit, _), (lit, _)) = (rmse(&mem, &smooth_sun), rmse(&mem, &flat_sun));
    let (deferred, _) = rmse(&mem_default, &deferred_default);
    println!(
        "forward: RMSE {flat:.2} ({:.2} % far) against {deferred:.2} deferred, lit {lit:.2}; --shading heights: {smooth:.2} ({:.2} % far), lit {smooth_lit:.2}",
        100.0 * flat_far,
        100.0 * smooth_far
    );
    assert!(flat < deferred + 0.2 && lit < 2.5, "forward: RMSE {flat:.2} against {deferred:.2} deferred, lit {lit:.2}");
    assert!(smooth < 4.5 && smooth_lit < 5.0, "--shading heights: RMSE {smooth:.2}, lit {smooth_lit:.2}");
}

/// `bench --stream` runs a path over an archive drawn streamed, under validation: every
/// frame drawn from the atlas and written to frames.csv, the summary with the frame
/// times, triangles, frames over the bound and 0 validation messages; what a streamed run
/// cannot do yet (`--raycast`) is refused by name; `--compare` and `--popping` run as in
/// memory.
#[test]
fn bench_runs_a_path_over_an_archive_drawn_streamed() {
    let dir = TempDir::new("gpu-stream-bench");
    let archive = dir.path().join("s.pmtiles");
    let a = archive.to_str().unwrap();
    let o = cli(&["prepare", "--synthetic", "1025", "--out", a]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let out = dir.path().join("b");
    let o = out.to_str().unwrap();
    let run = |extra: &[&str]| {
        let mut args = vec!["bench", "--heightmap", a, "--stream", "--frames", "12", "--size", "160x120"];
        args.extend(["--validation", "on", "--out", o]);
        args.extend(extra);
        cli(&args)
    };
    let r = run(&[]);
    assert!(r.status.success(), "{}", String::from_utf8_lossy(&r.stderr));
    let summary: serde_json::Value = serde_json::from_slice(&std::fs::read(out.join("summary.json")).unwrap()).unwrap();
    assert_eq!((summary["streamed"].as_bool(), summary["frames"].as_u64()), (Some(true), Some(12)), "{summary}");
    assert_eq!(summary["validation_messages"], 0, "{summary}");
    // The 12 timed frames and the untimed warm-up frame every run begins with.
    assert_eq!(summary["gpu"]["frames_drawn"], 13, "{summary}");
    assert!(summary["warmup_ms"].as_f64().is_some_and(|w| w > 0.0), "{summary}");
    assert_eq!(summary["gpu"]["frames_missing_blocks"], 0, "{summary}");
    assert!(summary["avg_fps"].as_f64().unwrap() > 0.0 && summary["mean_triangles"].as_f64().unwrap() > 1000.0);
    assert_eq!(summary["frames_over_bound"], summary["stream"]["frames_over_bound"]);
    // The in-memory bench's summary fields: the errors activity's generations the frames
    // took and their GPU time, the selection's time as the traversal's; and its plot.
    assert!(summary["error_updates"].as_u64().is_some_and(|u| u > 0), "{summary}");
    assert!(summary["median_error_update_ms"].as_f64().is_some_and(|t| t > 0.0), "{summary}");
    // Blocks were selected from them.
    assert!(summary["mean_blocks_bounded_by_errors"].as_f64().is_some_and(|b| b > 1.0), "{summary}");
    assert!(summary["median_traverse_ms"].as_f64().is_some_and(|t| t > 0.0), "{summary}");
    assert!(out.join("plot.png").exists());
    // Fidelity as in memory: three views along the path, four deltas each, against the
    // full-resolution frame; a larger delta draws fewer triangles, none more than full.
    let fidelity = summary["fidelity"].as_array().unwrap_or_else(|| panic!("no fidelity: {summary}"));
    assert_eq!(fidelity.len(), 12, "{summary}");
    for view in fidelity.chunks(4) {
        let f = |i: usize, k: &str| view[i][k].as_f64().unwrap();
        assert!((0..4).all(|i| f(i, "rmse").is_finite() && f(i, "triangles") <= f(i, "full_triangles")), "{view:?}");
        assert!(f(3, "triangles") < f(0, "triangles") && f(0, "delta") == 0.5 && f(3, "delta") == 5.0, "{view:?}");
    }
    // The terrain's facts, as every bench summary has them (synthetic: 30 m, 0.1 m a unit).
    assert_eq!(summary["samples"], serde_json::json!([1025, 1025]), "{summary}");
    assert_eq!(
        (summary["spacing_m"].clone(), summary["height_scale_m"].as_f64()),
        (serde_json::json!([30.0, 30.0]), Some(0.1f32 as f64)),
        "{summary}"
    );
    // frames.csv in the in-memory bench's columns: each frame's error generation (the
    // errors activity's, over the atlas) and its age, its GPU time where the device has
    // timestamps, the tiles held and the worst factor filled in.
    let csv = std::fs::read_to_string(out.join("frames.csv")).unwrap();
    assert_eq!(csv.lines().count(), 13, "{csv}");
    let mut lines = csv.lines();
    let header: Vec<&str> = lines.next().unwrap().split(',').collect();
    assert_eq!(
        (header[2], header[7], &header[20..]),
        ("traverse_ms", "error_generation", &["over_bound", "worst_factor", "tiles_held"][..])
    );
    let timed = summary["median_gpu_ms"].as_f64();
    assert!(timed.is_none_or(|t| t > 0.0), "{summary}");
    for row in lines.map(|l| l.split(',').collect::<Vec<_>>()) {
        assert_eq!(row.len(), header.len(), "{csv}");
        assert!(
            (if timed.is_some() { row[3].parse::<f64>().unwrap() > 0.0 } else { row[3].is_empty() })
                && row[7].parse::<u64>().unwrap() > 0
                && row[8].parse::<u64>().is_ok()
                && !row[21].is_empty()
                && row[22].parse::<u32>().unwrap() > 0,
            "{csv}"
        );
    }
    assert_eq!((summary["lod"].as_str(), summary["traversal_threads"].as_u64()), (Some("error"), Some(1)));
    assert_eq!(summary["error_mode"], "strict", "{summary}");
    // The baselines stream too: full resolution draws more triangles than the bound's
    // blocks, the distance rings another selection; neither morphs.
    let triangles = |extra: &[&str]| {
        let r = run(extra);
        assert!(r.status.success(), "{extra:?}: {}", String::from_utf8_lossy(&r.stderr));
        let s: serde_json::Value = serde_json::from_slice(&std::fs::read(out.join("summary.json")).unwrap()).unwrap();
        assert_eq!(
            (s["validation_messages"].as_u64(), s["mean_morphing_blocks"].as_f64()),
            (Some(0), Some(0.0)),
            "{s}"
        );
        assert_eq!(s["lod"].as_str(), Some(extra[1]), "{s}");
        s["mean_triangles"].as_f64().unwrap()
    };
    let bound = summary["mean_triangles"].as_f64().unwrap();
    let (full, rings) = (triangles(&["--lod", "full"]), triangles(&["--lod", "distance"]));
    println!("bench --stream triangles: bound {bound:.0}, full {full:.0}, rings {rings:.0}");
    assert!(full > 2.0 * bound && rings < full && rings != bound, "bound {bound}, full {full}, rings {rings}");
    // --compare as in memory: the bound's run against full resolution, the rings and the
    // ceiling (its own selections drawn again with none made), with the same figures.
    let r = run(&["--compare"]);
    assert!(r.status.success(), "--compare: {}", String::from_utf8_lossy(&r.stderr));
    let s: serde_json::Value = serde_json::from_slice(&std::fs::read(out.join("summary.json")).unwrap()).unwrap();
    let c = &s["compare"];
    for run in ["error", "full", "distance", "ceiling"] {
        assert_eq!(c[run]["frames"], 12, "{run}: {c}");
    }
    assert_eq!(c["error"]["mean_triangles"], c["ceiling"]["mean_triangles"], "the ceiling draws the same blocks: {c}");
    // Its full run is `--lod full` alone (its first view's tiles read first: without that,
    // a review measured 437,664 triangles a frame against 538,549 alone on Puget Sound
    // 1k; frames do not wait for tiles, so the two may differ by a frame drawn coarser).
    let compared_full = c["full"]["mean_triangles"].as_f64().unwrap();
    assert!(compared_full > 0.95 * full, "full {compared_full} in --compare against {full} alone: {c}");
    assert!(c["triangles_full_over_error"].as_f64().unwrap() > 2.0, "{c}");
    assert!(c["p99_excess_over_ceiling_ms"].is_number() && c["stall_target_ms"].is_number(), "{c}");
    assert_eq!(s["validation_messages"], 0, "{s}");
    let ceiling = std::fs::read_to_string(out.join("ceiling.csv")).unwrap();
    assert_eq!(ceiling.lines().count(), 13, "{ceiling}");
    // --popping as in memory: each frame against the one before, less the full run's
    // change; and the change due to the LOD selection alone, on a keyed background.
    let r = run(&["--popping"]);
    assert!(r.status.success(), "--popping: {}", String::from_utf8_lossy(&r.stderr));
    let s: serde_json::Value = serde_json::from_slice(&std::fs::read(out.join("summary.json")).unwrap()).unwrap();
    let p = &s["popping"];
    assert_eq!((p["frame_pairs"].as_u64(), p["morph"].as_bool()), (Some(11), Some(true)), "{p}");
    assert!(p["p99_excess"].is_number() && p["max_lod_change_rmse"].as_f64().is_some_and(|m| m >= 0.0), "{p}");
    assert_eq!(s["validation_messages"], 0, "{s}");
    let csv = std::fs::read_to_string(out.join("frames.csv")).unwrap();
    let rows: Vec<Vec<&str>> = csv.lines().skip(2).map(|l| l.split(',').collect()).collect();
    assert!(rows.iter().all(|r| !r[12].is_empty() && !r[13].is_empty() && !r[14].is_empty()), "{csv}");
    // Paced on lavapipe's one queue, one generation at a time (the first run); free, a
    // request every frame, the next generation is submitted while the last one runs
    // (uploads and errors passes, each with its own command buffer, staging and target),
    // under synchronization validation, every block finding its layer.
    assert_eq!(summary["most_generations_in_flight"], 1, "{summary}");
    let free = ["--error-pacing", "free", "--refresh-at", "0", "--update-share", "1"];
    let r = run(&free);
    assert!(r.status.success(), "free pacing: {}", String::from_utf8_lossy(&r.stderr));
    let s: serde_json::Value = serde_json::from_slice(&std::fs::read(out.join("summary.json")).unwrap()).unwrap();
    assert_eq!(
        (s["most_generations_in_flight"].as_u64(), s["validation_messages"].as_u64()),
        (Some(2), Some(0)),
        "{s}"
    );
    assert!(s["error_updates"].as_u64().is_some_and(|u| u >= 6), "{s}");
    assert_eq!(s["gpu"]["frames_missing_blocks"], 0, "{s}");
    // Ray-cast blocks over tiles: counted per frame, as in memory.
    let r = run(&["--raycast", "all"]);
    assert!(r.status.success(), "{}", String::from_utf8_lossy(&r.stderr));
    let s: serde_json::Value = serde_json::from_slice(&std::fs::read(out.join("summary.json")).unwrap()).unwrap();
    assert_eq!(s["validation_messages"], 0, "{s}");
    assert!(s["mean_raycast_blocks"].as_f64().is_some_and(|b| b >= 0.0), "{s}");
}

/// `render --stream --audit` audits in the archive's block layout (one square of
/// 2^n + 1 samples), which is not the in-memory one for narrow or small terrains: an
/// adversarial review found the audit, in the in-memory layout, reading past its block
/// map (a panic) on a 2000 x 34 field and reporting samples uncovered on a 40 x 40 one,
/// where the frames were right. Random heights from -5 to 5, 10 m apart, from the
/// review's cameras.
#[test]
fn a_streamed_frame_of_a_narrow_terrain_audits_in_the_archives_layout() {
    let dir = TempDir::new("gpu-stream-narrow");
    for (w, h, camera, look_at) in [
        (2000, 34, "20050,40,170", "10000,0,170"),
        (40, 40, "200,40,450", "200,0,200"),
        (34, 2000, "170,40,20050", "170,0,10000"),
    ] {
        let raw = dir.path().join(format!("f{w}x{h}.f32"));
        let mut state = 9u64;
        let bytes: Vec<u8> = (0..w * h)
            .flat_map(|_| {
                state = state.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
                (((state >> 40) as f32 / (1u64 << 24) as f32) * 10.0 - 5.0).to_le_bytes()
            })
            .collect();
        std::fs::write(&raw, bytes).unwrap();
        let archive = dir.path().join(format!("f{w}x{h}.pmtiles"));
        let size = format!("{w}x{h}");
        let o = cli(&["prepare", raw.to_str().unwrap(), "--raw-size", &size, "--spacing", "10", "--height-scale", "1"]
            .into_iter()
            .chain(["--out", archive.to_str().unwrap()])
            .collect::<Vec<_>>());
        assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
        let png = dir.path().join("r.png");
        let o = cli(&[
            "render",
            "--heightmap",
            archive.to_str().unwrap(),
            "--stream",
            "--audit",
            "--validation",
            "on",
            "--size",
            "256x256",
            "--camera",
            camera,
            "--look-at",
            look_at,
            "--out",
            png.to_str().unwrap(),
        ]);
        assert!(o.status.success(), "{size}: {}", String::from_utf8_lossy(&o.stderr));
        let r: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
        assert_eq!(r["within_bound"], true, "{size}: {r}");
        assert_eq!(
            (r["audit_within_delta"].as_bool(), r["uncovered_samples"].as_u64()),
            (Some(true), Some(0)),
            "{size}: {r}"
        );
        assert_eq!(r["gpu"]["validation_messages"], 0, "{size}: {r}");
    }
}

/// Parts of streamed blocks whose boxes lie outside the frustum (widened by a pixel) are
/// left out, and no pixel shows it: at 96 low views around and across a rough field
/// (cliffs, ridges, a spike; many blocks crossing the image's edges) the frame drawn with
/// them left out is the frame drawn whole, bit for bit, under validation. Mutation: a
/// frustum narrowed by 40 pixels leaves out visible parts, and the frames differ.
#[test]
fn streamed_parts_outside_the_frustum_are_never_seen() {
    let hf = common::rough();
    let dir = TempDir::new("gpu-stream-parts");
    let archive = common::archive_of(&hf, &dir);
    let grid = Grid::from_meta(&archive.meta);
    let device = common::gpu();
    {
        let mut s = Streamer::new(archive, grid, 1 << 30);
        let atlas = HeightAtlas::new(&device, &grid, 64 << 20).unwrap();
        let lit = OwnLighting::everything_lit(&device).unwrap();
        s.attach(Box::new(atlas.feed()), HeightAtlas::cache_tiles(atlas.layer_count()));
        let mut renderer = StreamedRenderer::new(&device, draw::layout(&grid), 160, 120).unwrap();
        let (mut hidden, mut parts, mut caught) = (0usize, 0usize, 0usize);
        let mut poses = 0;
        for i in 0..96 {
            let a = f64::from(i) * std::f64::consts::TAU / 24.0;
            let r = 300.0 + 250.0 * f64::from(i % 4);
            let (x, z) = (1500.0 + r * a.cos(), 2500.0 + r * a.sin());
            let ground = f64::from(hf.surface_height(x as f32, z as f32));
            let p = DVec3::new(x, ground + 15.0 + 25.0 * f64::from(i % 3), z);
            // Level with the ground or a little down, turned off the radius.
            let heading = a + 1.2 + 0.4 * f64::from(i % 5);
            let t = p + DVec3::new(heading.cos() * 1000.0, -40.0 * f64::from(i % 2), heading.sin() * 1000.0);
            let view = View::look_at(p, t, 50.0, 160, 120, 1.0);
            let sel = settled(&mut s, &view);
            let whole = draw::stitched_blocks(&grid, &s.cache, &sel);
            let fv = frame_view(&grid, &view, &lit);
            let mut culled = whole.clone();
            let n = draw::hide_parts_outside(&grid, &s.cache, fv.anchor, &fv.cam, &mut culled);
            hidden += n;
            parts += whole.len() * 16;
            let (a_px, a) = renderer.render(&atlas, &fv, &whole).unwrap();
            let (b_px, b) = renderer.render(&atlas, &fv, &culled).unwrap();
            assert_eq!(b.hidden_parts, n as u64, "pose {i}");
            assert_eq!(a.triangles - b.triangles, n as u64 * draw::layout(&grid).triangles_per_part(), "pose {i}");
            assert!(a_px == b_px, "pose {i}: {n} parts left out changed the frame");
            let mut narrowed = whole.clone();
            draw::hide_parts_outside_by(&grid, &s.cache, fv.anchor, &fv.cam, -40.0, &mut narrowed);
            let (c_px, _) = renderer.render(&atlas, &fv, &narrowed).unwrap();
            caught += usize::from(c_px != a_px);
            poses += 1;
        }
        eprintln!(
            "{hidden} of {parts} parts outside the frustum; a narrowed frustum caught at {caught} of {poses} poses"
        );
        assert_eq!(poses, 96);
        assert!(hidden * 20 > parts, "{hidden} of {parts} parts outside the frustum: the poses test little");
        assert!(caught * 2 > poses, "mutation: a narrowed frustum changed only {caught} of {poses} frames");
    }
    common::finish(device);
}

/// `render --stream` of `input` under validation, its temporary files in `tmp` and its
/// image in `out`, silent.
fn spawn_streamed_render(
    input: &std::path::Path,
    tmp: &TempDir,
    out: &std::path::Path,
    extra: &[&str],
) -> std::process::Child {
    std::process::Command::new(env!("CARGO_BIN_EXE_vkterrain"))
        .args(["render", "--heightmap", input.to_str().unwrap(), "--stream", "--validation", "on"])
        .args(extra)
        .args(["--out", out.join("x.png").to_str().unwrap()])
        .env("TMPDIR", tmp.path())
        .env("RUST_LOG", "error")
        .stdout(std::process::Stdio::null())
        .stderr(std::process::Stdio::piped())
        .spawn()
        .unwrap()
}

/// A stop signal while a terrain file is cut into tiles for `render --stream` ends the
/// run with 128 + the signal and leaves nothing behind (no output, nothing in the
/// temporary directory); so does one once the tiles are cut, while the frame is drawn
/// and audited (the cutting's handlers are obeyed: the run used to draw on and exit 0).
#[test]
fn a_stream_cut_from_a_file_and_stopped_leaves_nothing() {
    let ps = common::data("puget_sound/ps_height_4k.jpg");
    // (signal, exit code, the stderr line after which it is sent, extra options)
    let cases = [
        ("TERM", 143, "into tiles in memory", &["--size", "64x48"][..]),
        ("INT", 130, "into tiles in memory", &["--size", "64x48"][..]),
        ("TERM", 143, "drawn from its tiles", &["--audit", "--size", "640x480"][..]),
    ];
    for (signal, code, after, extra) in cases {
        let tmp = TempDir::new("gpu-stream-stop");
        let out = tmp.path().join("out");
        std::fs::create_dir(&out).unwrap();
        let mut child = spawn_streamed_render(&ps, &tmp, &out, extra);
        // Wait for the line (reading it, not a fixed sleep), then stop the run.
        let mut lines = std::io::BufRead::lines(std::io::BufReader::new(child.stderr.take().unwrap()));
        let seen = lines.by_ref().map_while(Result::ok).any(|l| l.contains(after));
        assert!(seen, "SIG{signal}: the run ended before '{after}'");
        let kill =
            std::process::Command::new("kill").args([&format!("-{signal}"), &child.id().to_string()]).status().unwrap();
        assert!(kill.success());
        lines.for_each(drop);
        let status = child.wait().unwrap();
        assert_eq!(status.code(), Some(code), "SIG{signal} after '{after}': {status:?}");
        assert!(
            std::fs::read_dir(&out).unwrap().next().is_none(),
            "SIG{signal} after '{after}': an output was written"
        );
        let left: Vec<_> = std::fs::read_dir(tmp.path()).unwrap().flatten().map(|e| e.file_name()).collect();
        assert_eq!(left, ["out"], "SIG{signal} after '{after}': left in the temporary directory");
    }
}

/// An adversarial review's field (flat 16-bit ground with one LOD-1 vertex raised 6
/// units: `D_1 = 0` everywhere, so the squares around it allow no morph at all), seen from
/// just above with the raised block's neighbour 4 LODs coarser: the stitched fan triangles
/// along that edge carry the next square's morphed vertices into samples of a square
/// whose own terms were 0. Morphed, it audited at 5.95 px (delta 1) while `--morph off`
/// audits at 0; the strip is now paid with the whole edge's largest move.
#[test]
fn a_stitched_fan_carries_no_unpaid_morph() {
    let dir = TempDir::new("gpu-stream-fan");
    let (n, base, (vx, vz), w) = (2049u32, 30000u16, (524u32, 1028u32), 6.0f64);
    let vert = |x: u32, z: u32| if (x, z) == (vx, vz) { w } else { 0.0 };
    let img = image::ImageBuffer::<image::Luma<u16>, Vec<u16>>::from_fn(n, n, |x, z| {
        if x.abs_diff(vx) > 3 || z.abs_diff(vz) > 3 {
            return image::Luma([base]);
        }
        let (x0, z0) = (x / 2 * 2, z / 2 * 2);
        let (u, v) = (f64::from(x - x0) / 2.0, f64::from(z - z0) / 2.0);
        let (a, c, i, g) = (vert(x0, z0), vert(x0 + 2, z0), vert(x0 + 2, z0 + 2), vert(x0, z0 + 2));
        let h = if u >= v { a + u * (c - a) + v * (i - c) } else { a + v * (g - a) + u * (i - g) };
        image::Luma([base + h as u16])
    });
    let field = dir.path().join("fan.png");
    img.save(&field).unwrap();
    let out = dir.path().join("fan-out.png");
    let o = cli(&[
        "render",
        "--heightmap",
        field.to_str().unwrap(),
        "--spacing",
        "30",
        "--height-scale",
        "0.1",
        "--stream",
        "--audit",
        "--size",
        "320x240",
        "--validation",
        "on",
        "--camera",
        "15508,3001.5,30748",
        "--look-at",
        "15510,3000,30750",
        "--out",
        out.to_str().unwrap(),
    ]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let r: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    assert_eq!(r["within_bound"], true, "{r}");
    assert!(r["morphing"].as_u64().unwrap() > 0, "{r}");
    assert_eq!(r["audit_within_delta"], true, "{r}");
    assert!(r["max_audited_error_px"].as_f64().unwrap() <= 1.0, "{r}");
    assert_eq!(r["gpu"]["validation_messages"], 0, "{r}");
}

/// Deferred streamed frames (the default: the blocks' depth, then one shading pass whose
/// normals and sea share come from the lighting map's heights as memory's come from its
/// samples, or, where those are too coarse for the pixel, from the surface as drawn)
/// against the same frames shaded forward (`--pixels forward`: every fragment, flat
/// normals, the vertices' sea flags) and the terrain drawn in memory. At high, low and
/// horizon-level views over Puget Sound 1k (water) and a crafted field of a cliff,
/// one-sample walls and a lake whose 300 x 200 samples leave a margin in their block grid
/// (clipped by the depth pass where the forward pass discards: the plain background shows
/// there in both), the map holds every sample and the deferred frame is shaded as in
/// memory; over Puget Sound 4k (a map of every other sample) close views take the drawn
/// surface's normals and water. A frame shaded wrongly (the margin shown, the held
/// samples misread, a close view from samples too coarse for it) is far from memory's.
#[test]
fn deferred_streamed_frames_are_shaded_as_in_memory() {
    let dir = TempDir::new("gpu-stream-deferred");
    let prepare = |input: &str, extra: &[&str], name: &str| {
        let out = dir.path().join(name);
        let mut args = vec!["prepare", input];
        args.extend(extra);
        args.extend(["--out", out.to_str().unwrap()]);
        let o = cli(&args);
        assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
        out
    };
    let ps = prepare(common::data("puget_sound/ps_height_1k.png").to_str().unwrap(), &[], "ps.pmtiles");
    let ps4k = prepare(
        common::data("puget_sound/ps_height_4k.jpg").to_str().unwrap(),
        &["--spacing", "40", "--height-scale", "17.2"],
        "ps4k.pmtiles",
    );
    let crafted = common::field(300, 200, [2.0, 2.0], |x, z| {
        let cliff = if x > 150 { 30.0 } else { 0.0 };
        let wall = if z % 40 == 20 { 20.0 } else { 0.0 };
        let lake = (x as f32 - 60.0).hypot(z as f32 - 100.0) < 30.0;
        if lake {
            0.0
        } else {
            5.0 + cliff + wall + ((x as f32 * 0.11).sin() * (z as f32 * 0.07).cos()) * 8.0
        }
    });
    drop(common::archive_of(&crafted, &dir));
    let crafted = dir.path().join("t.pmtiles");
    let fbm = prepare("--synthetic", &["2050"], "fbm.pmtiles");
    let png = dir.path().join("f.png");
    // The frame, how its pixels were shaded ("memory" when not streamed), and the
    // samples between the lighting map's heights (streamed frames).
    let frame = |archive: &std::path::Path, extra: &[&str]| {
        let mut args = vec!["render", "--heightmap", archive.to_str().unwrap()];
        args.extend(["--validation", "on", "--size", "320x240", "--background", "1,0,1"]);
        args.extend(["--out", png.to_str().unwrap()]);
        args.extend(extra);
        let o = cli(&args);
        assert!(o.status.success(), "{extra:?}: {}", String::from_utf8_lossy(&o.stderr));
        let r: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
        let streamed = r["streamed"] == true;
        let messages = if streamed { &r["gpu"]["validation_messages"] } else { &r["validation_messages"] };
        assert_eq!(messages, 0, "{r}");
        let pixels = if streamed { r["pixels"].as_str().unwrap() } else { "memory" };
        let stride = r["gpu"]["lighting"]["heights_samples_apart"].as_u64().unwrap_or(0);
        (pixels.to_string(), image::open(&png).unwrap().to_rgba8(), stride)
    };
    let magenta = |img: &image::RgbaImage| img.pixels().filter(|p| p[0] > 250 && p[1] < 5 && p[2] > 250).count();
    // Water: clearly bluer than green and red (the ramp has no such colour).
    let water = |img: &image::RgbaImage| {
        img.pixels()
            .filter(|p| i32::from(p[2]) > i32::from(p[1]) + 15 && i32::from(p[2]) > i32::from(p[0]) + 40)
            .count()
    };
    let difference = |a: &image::RgbaImage, b: &image::RgbaImage| image_difference(a.as_raw(), b.as_raw());
    // Pose, and the most RMSE and share of pixels over 16 levels against memory.
    let views: [(&std::path::Path, [&str; 2], u64, f64, f64); 13] = [
        (&ps, ["30000,900,30000", "90000,0,90000"], 1, 2.5, 0.005),
        (&ps, ["60000,9000,10000", "60000,0,60000"], 1, 2.5, 0.005),
        // Low, towards the horizon.
        (&ps, ["20000,700,70000", "120000,300,70000"], 1, 2.5, 0.005),
        (&ps, ["5000,400,5000", "100000,0,100000"], 1, 2.5, 0.005),
        // Over the crafted field's far corner: the margin beyond x = 299, z = 199. Its
        // selection is memory's, and both shade from the same gradient map (RMSE 0.01
        // to 1.3 here; 2.5 and more with the map's gradients or sea flags wrong).
        (&crafted, ["560,200,360", "598,0,398"], 1, 1.6, 0.0005),
        (&crafted, ["-40,60,-30", "300,0,200"], 1, 0.3, 0.0005),
        // Low over the lake, the walls' silhouettes against those behind them.
        (&crafted, ["60,14,5", "60,5,200"], 1, 0.3, 0.0005),
        (&crafted, ["250,45,100", "0,20,100"], 1, 0.3, 0.0005),
        // Every other sample held: from far, as memory; close over a coast, the drawn
        // surface (terraced by the JPEG's steps, which memory's normals smooth over).
        (&ps4k, ["60000,2000,20000", "90000,0,60000"], 2, 3.5, 0.012),
        (&ps4k, ["84000,3000,10000", "84000,0,10001"], 2, 5.0, 0.025),
        (&ps4k, ["83700,250,9300", "83700,0,9301"], 2, 5.0, 0.035),
        // Close over smooth relief (2050^2: every other sample held): the drawn normals
        // (RMSE 4.4 and 4.8 against memory here; 7.4 and 7.6 with every drawn normal
        // facing up).
        (&fbm, ["30000,4500,30000", "30400,0,30400"], 2, 5.5, 0.04),
        (&fbm, ["20000,5000,20000", "20600,0,20600"], 2, 5.5, 0.04),
    ];
    for (archive, [camera, look_at], held_stride, most_rmse, most_far) in views {
        let pose = ["--camera", camera, "--look-at", look_at];
        let (pixels, deferred, stride) = frame(archive, &[&pose[..], &["--stream"]].concat());
        let (forward_pixels, forward, _) = frame(archive, &[&pose[..], &["--stream", "--pixels", "forward"]].concat());
        let (memory_pixels, memory, _) = frame(archive, &pose);
        assert_eq!((&*pixels, &*forward_pixels, &*memory_pixels), ("deferred", "forward", "memory"), "{camera}");
        assert_eq!(stride, held_stride, "{camera}");
        let ((rmse, far), (forward_rmse, _)) = (difference(&memory, &deferred), difference(&memory, &forward));
        let (bd, bf) = (magenta(&deferred), magenta(&forward));
        let (wd, wm) = (water(&deferred), water(&memory));
        println!(
            "{camera}: against memory RMSE {rmse:.2} ({:.2} % over 16 levels) deferred, {forward_rmse:.2} forward; \
             background {bd} / {bf} forward; water {wd} / {wm} in memory",
            100.0 * far
        );
        // The background (the margin included) is the forward frame's: only pixel
        // centres on the true extent's edge may fall either way.
        assert!(bd.abs_diff(bf) * 500 <= (320 * 240), "{camera}: background pixels {bd} deferred, {bf} forward");
        assert!(rmse < most_rmse && far < most_far, "{camera}: RMSE {rmse:.2}, {:.2} % over 16 levels", 100.0 * far);
        // Where the held samples are the terrain's, forward frames shade from them too.
        if held_stride == 1 {
            let (forward_far, wf) = (difference(&memory, &forward).1, water(&forward));
            assert!(forward_rmse < most_rmse && forward_far < most_far, "{camera}: forward RMSE {forward_rmse:.2}");
            assert!(wf.abs_diff(wm) * 10 <= wm.max(100), "{camera}: water pixels {wf} forward, {wm} in memory");
        }
        assert!(wd.abs_diff(wm) * 10 <= wm.max(100), "{camera}: water pixels {wd} deferred, {wm} in memory");
    }
    // From 2 x 10^5 spacings out, depth no longer gives the points forward shading shades
    // (as in memory): the frame is shaded forward, and says so.
    let far_out = ["--stream", "--camera", "400000,100000,200", "--look-at", "300,0,200"];
    assert_eq!(frame(&crafted, &far_out).0, "forward");
    // And as asked, or coloured by LOD (which needs the block that drew each pixel), or
    // with normals from the tiles' heights (which the shading pass does not reach).
    assert_eq!(frame(&ps, &["--stream", "--colour-by-lod"]).0, "forward");
    assert_eq!(frame(&ps, &["--stream", "--shading", "heights"]).0, "forward");
}

/// Frames at `view` until the selection is within the bound and every block's error
/// that can come from the errors activity does (tiles and errors settled after each).
fn settled_with_errors(s: &mut Streamer, view: &View) -> Selection {
    for _ in 0..16 {
        let sel = s.frame(view, None, 1.0, 1.0);
        if sel.within_bound() && sel.errors_from_tiles == 0 && sel.errors_generation > 0 {
            return sel;
        }
        s.settle();
    }
    panic!("not settled with errors");
}

/// The plain-Rust error of every block of `key`'s own level for the camera `view`: the
/// largest over its groups of `D * height_scale * kappa / distance(camera, group box)`,
/// the box spanning the group's quad between its corners' range widened by `D`, in f64.
fn block_errors_oracle(grid: &Grid, tile: &TileData, view: &View) -> Vec<f64> {
    let (anchor, cam) = view.relative(grid);
    let key = tile.key;
    let (quads, stride) = (grid.block_quads, 1i64 << key.level);
    let per_side = grid.tile_quads / quads;
    let span = grid.tile_span(key.level) as i64;
    let p = cam.position.as_dvec3();
    let kappa = f64::from(cam.kappa());
    let mut out = vec![0.0f64; per_side * per_side];
    for gz in 0..grid.tile_quads {
        for gx in 0..grid.tile_quads {
            let corners =
                [tile.vertex(gx, gz), tile.vertex(gx + 1, gz), tile.vertex(gx, gz + 1), tile.vertex(gx + 1, gz + 1)];
            let d = f64::from(tile.group_d(
                grid,
                u32::from(key.level),
                key.tx as usize * grid.tile_quads + gx,
                key.tz as usize * grid.tile_quads + gz,
            ));
            let lo = corners.iter().fold(f64::INFINITY, |a, &c| a.min(f64::from(c))) - d;
            let hi = corners.iter().fold(f64::NEG_INFINITY, |a, &c| a.max(f64::from(c))) + d;
            let x0 = (i64::from(key.tx) * span + gx as i64 * stride - anchor[0]) as f64 * grid.spacing[0];
            let z0 = (i64::from(key.tz) * span + gz as i64 * stride - anchor[1]) as f64 * grid.spacing[1];
            let min = DVec3::new(x0, lo * grid.height_scale, z0);
            let max = DVec3::new(
                x0 + stride as f64 * grid.spacing[0],
                hi * grid.height_scale,
                z0 + stride as f64 * grid.spacing[1],
            );
            let dist = (min - p).max(p - max).max(DVec3::ZERO).length().max(f64::from(cam.near));
            let b = (gz / quads) * per_side + gx / quads;
            out[b] = out[b].max(d * grid.height_scale * kappa / dist);
        }
    }
    out
}

/// Settles each of [`views`] with a generation of errors and compares every block error
/// read back with [`block_errors_oracle`] (the deviations rounded up to half floats:
/// never below it, at most 0.1 % above); each selection audits within delta (blocks of
/// `layout`). Returns the errors compared, the blocks bounded by them, and each view's
/// blocks.
fn errors_are_the_oracle(
    hf: &Heightfield,
    layout: &vkterrain::lod::block::BlockLayout,
    s: &mut Streamer,
    atlas: &HeightAtlas,
) -> (usize, usize, Vec<usize>) {
    let grid = s.grid;
    let k = layout.k();
    let (mut compared, mut from_gpu, mut blocks) = (0usize, 0usize, Vec::new());
    for (i, view) in views().iter().enumerate() {
        let sel = settled_with_errors(s, view);
        from_gpu += sel.errors_from_gpu;
        let errors = atlas.feed().errors().expect("a generation");
        assert_eq!(errors.position, view.position, "k {k}, pose {i}: the errors are this camera's");
        for (key, got) in &errors.tiles {
            let tile = s.cache.peek(*key).expect("a shaded tile is held");
            let want = block_errors_oracle(&grid, tile, view);
            assert_eq!(got.len(), want.len(), "k {k}, pose {i}: tile {key:?}'s blocks");
            for (b, (g, w)) in got.iter().zip(&want).enumerate() {
                let g = f64::from(*g);
                assert!(
                    g >= w * (1.0 - 1e-4) && g <= w * 1.001 + 1e-9,
                    "k {k}, pose {i}: tile {key:?} block {b}: {g} against {w}"
                );
                compared += 1;
            }
        }
        let worst = sel
            .stitched
            .iter()
            .map(|b| vkterrain::lod::audit::audit_block(hf, layout, b, &view.absolute()))
            .fold(0.0f32, f32::max);
        assert!(worst <= 1.001, "k {k}, pose {i}: a block audits at {worst} px");
        blocks.push(sel.blocks.len());
    }
    (compared, from_gpu, blocks)
}

/// The errors activity over the atlas (SPEC 4 and 8): a settled frame takes every
/// block's error from the GPU's generation (but the top tile's coarser blocks, which
/// its summary bounds); each error read back is the plain-Rust per-group bound (the
/// deviations rounded up to half floats: never below it, at most 0.1 % above); the
/// selection audits within delta against the full heightfield; and a readback corrupted
/// to a quarter changes the selection and fails the audit.
#[test]
fn block_errors_over_the_atlas_are_the_cpu_bound_and_the_selection_comes_from_them() {
    use vkterrain::lod::audit::audit_block;
    use vkterrain::lod::block::BlockLayout;
    let hf = common::rough();
    let dir = TempDir::new("gpu-stream-errors");
    let archive = common::archive_of(&hf, &dir);
    let layout = BlockLayout::of(&hf, 33).unwrap();
    let device = common::gpu();
    // The smallest and the largest blocks a tile takes (`--block`), their generations
    // paced free (the next submitted while the last runs, two slots in turn); then the
    // paper's blocks, paced.
    for k in [9, 129] {
        let grid = Grid::from_meta(&archive.meta).with_block(k).unwrap();
        let mut s = Streamer::new(archive.clone(), grid, 1 << 30);
        let atlas = HeightAtlas::new(&device, &grid, 64 << 20).unwrap();
        atlas.set_pacing(vkterrain::errors::activity::Pacing::Free, &device);
        s.attach(Box::new(atlas.feed()), HeightAtlas::cache_tiles(atlas.layer_count()));
        let layout = BlockLayout::of(&hf, k).unwrap();
        let (compared, from_gpu, _) = errors_are_the_oracle(&hf, &layout, &mut s, &atlas);
        eprintln!("k {k}: {compared} block errors compared, {from_gpu} blocks bounded by them, {} generations in flight at most", atlas.most_in_flight());
        // Measured: 7,168 and 52 compared, 417 and 28 blocks bounded by them.
        assert!(compared >= 40 && from_gpu >= 20, "k {k}: {compared} compared, {from_gpu} bounded by them");
        assert_eq!(atlas.failure(), None);
    }
    let grid = Grid::from_meta(&archive.meta);
    let mut s = Streamer::new(archive, grid, 1 << 30);
    let atlas = HeightAtlas::new(&device, &grid, 64 << 20).unwrap();
    s.attach(Box::new(atlas.feed()), HeightAtlas::cache_tiles(atlas.layer_count()));
    let worst_audit = |sel: &Selection, v: &View| {
        sel.stitched.iter().map(|b| audit_block(&hf, &layout, b, &v.absolute())).fold(0.0f32, f32::max)
    };
    let (compared, from_gpu, blocks) = errors_are_the_oracle(&hf, &layout, &mut s, &atlas);
    assert!(compared >= 64 && from_gpu >= 50, "{compared} block errors compared, {from_gpu} blocks bounded by them");

    // A descent with one generation, computed at its start: the errors thread may take
    // no more than a thousandth of the wall time, so none follows during the flight, and
    // every frame takes that one, corrected for how far the camera has come (the tiles
    // of the whole descent are read first). Every frame audits within delta.
    atlas.set_update_share(1e-3);
    let look = |p: DVec3| View::look_at(p, p + DVec3::new(400.0, -60.0, 900.0), 45.0, 320, 240, 1.0);
    let (start, end) = (DVec3::new(1000.0, 400.0, 1000.0), DVec3::new(1600.0, 150.0, 2400.0));
    for i in 1..=16 {
        settled(&mut s, &look(start.lerp(end, f64::from(i) / 16.0)));
    }
    let first = settled_with_errors(&mut s, &look(start));
    let (mut audited, mut corrected) = (0, 0);
    for i in 1..=16 {
        let view = look(start.lerp(end, f64::from(i) / 16.0));
        let sel = s.frame(&view, None, 1.0, 1.0);
        assert!(sel.within_bound(), "step {i}: every tile is held");
        assert_eq!(sel.errors_generation, first.errors_generation, "step {i}: one generation for the flight");
        let worst = worst_audit(&sel, &view);
        assert!(worst <= 1.001, "step {i}: a block audits at {worst} px");
        audited += 1;
        corrected += usize::from(sel.errors_from_gpu > 0 && sel.errors_stale_worst > 1.5);
    }
    assert!(corrected >= 8, "{corrected} of {audited} frames took errors corrected by more than 1.5x");
    atlas.set_update_share(0.05);

    // The same poses with every error read back a quarter of what it is: fewer blocks,
    // over the bound (the poses follow each other far apart: each asks anew).
    atlas.corrupt_errors(0.25);
    let (mut over, mut corrupted) = (0, Vec::new());
    for (i, view) in views().iter().enumerate() {
        let sel = settled_with_errors(&mut s, view);
        assert!(sel.blocks.len() <= blocks[i], "pose {i}: {} blocks corrupted, {} not", sel.blocks.len(), blocks[i]);
        corrupted.push(sel.blocks.len());
        over += usize::from(worst_audit(&sel, view) > 1.001);
    }
    assert!(corrupted.iter().sum::<usize>() < blocks.iter().sum(), "{corrupted:?} blocks corrupted, {blocks:?} not");
    assert!(over > 0, "a corrupted readback passes the audit at every pose");
    assert_eq!(atlas.failure(), None);
}

/// A raw file larger than one image (lavapipe's 16384 side) is drawn from its tiles
/// without being asked to: its size is the one `--raw-size` gives (GDAL cannot read a
/// raw file's header), not unknown.
#[test]
fn a_raw_file_larger_than_one_image_is_drawn_from_tiles() {
    let dir = TempDir::new("gpu-stream-raw-strip");
    let (w, h) = (16641usize, 300usize);
    let path = dir.path().join("strip.f32");
    let bytes: Vec<u8> =
        (0..w * h).flat_map(|i| (((i % w) as f32 * 0.01).sin() * 50.0 + (i / w) as f32 * 0.1).to_le_bytes()).collect();
    std::fs::write(&path, bytes).unwrap();
    let png = dir.path().join("o.png");
    let o = cli(&[
        "render",
        path.to_str().unwrap(),
        "--raw-size",
        "16641x300",
        "--spacing",
        "10",
        "--height-scale",
        "1",
        "--size",
        "64x48",
        "--validation",
        "on",
        "--out",
        png.to_str().unwrap(),
    ]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let r: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    assert_eq!((r["streamed"].as_bool(), r["validation_messages"].as_u64()), (Some(true), Some(0)), "{r}");
}

/// Occlusion culling over tiles (SPEC section 10, from the tiles' summaries): at low,
/// horizon-level poses over the rough field and over a cliff with thin pillars (a plain
/// hidden behind the cliff's edge, the pillars' tops showing over it), the frame drawn
/// without the hidden blocks and parts is the frame drawn whole, bit for bit, under
/// validation. Mutations of the sweep's rule (occluders at their blocks' highest drawn
/// height; parts tested at their lowest vertex) hide visible terrain, and the frames
/// differ.
#[test]
fn streamed_occlusion_culling_hides_nothing_visible() {
    use vkterrain::lod::occlusion::Rule;
    let cliff_pillars = common::field(513, 513, 2.0, |x, z| {
        let wobble = ((z as f32) * 0.3).sin() * 0.5;
        if x < 256 {
            60.0 + wobble
        } else if x % 9 == 4 && z % 9 == 4 {
            80.0
        } else {
            wobble
        }
    });
    let device = common::gpu();
    let (mut hidden, mut parts, mut poses, mut culled_poses) = (0usize, 0usize, 0usize, 0usize);
    let mut caught = [0usize; 2];
    for (name, hf) in [("rough", common::rough()), ("cliff with pillars", cliff_pillars)] {
        let dir = TempDir::new("gpu-stream-occlusion");
        let archive = common::archive_of(&hf, &dir);
        let grid = Grid::from_meta(&archive.meta);
        let mut s = Streamer::new(archive, grid, 1 << 30);
        let atlas = HeightAtlas::new(&device, &grid, 64 << 20).unwrap();
        let lit = OwnLighting::everything_lit(&device).unwrap();
        s.attach(Box::new(atlas.feed()), HeightAtlas::cache_tiles(atlas.layer_count()));
        let mut renderer = StreamedRenderer::new(&device, draw::layout(&grid), 160, 120).unwrap();
        let all = draw::layout(&grid).all_parts();
        let (wx, wz) = hf.world_extent();
        let mut rng = 0x9e37_79b9_7f4a_7c15_u64;
        let mut next = || {
            rng = rng.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
            (rng >> 11) as f64 / (1u64 << 53) as f64
        };
        for i in 0..48 {
            let (x, z) = (f64::from(wx) * (0.05 + 0.9 * next()), f64::from(wz) * (0.05 + 0.9 * next()));
            let ground = f64::from(hf.surface_height(x as f32, z as f32));
            let p = DVec3::new(x, ground + f64::from(hf.spacing.min()) + 30.0 * next(), z);
            let (yaw, pitch) = (next() * std::f64::consts::TAU, 0.05 - 0.5 * next());
            let dir = DVec3::new(yaw.cos() * pitch.cos(), pitch.sin(), yaw.sin() * pitch.cos());
            // One pose in four with a near plane 40 units out, which at some poses meets
            // the ground ahead: those frames are not culled (`near plane at the ground`).
            let near = if i % 4 == 3 { 40.0 } else { 0.1 };
            let view = View::look_at(p, p + dir * 100.0, 30.0 + 40.0 * next() as f32, 160, 120, near);
            let sel = settled(&mut s, &view);
            let whole = draw::stitched_blocks(&grid, &s.cache, &sel);
            let fv = frame_view(&grid, &view, &lit);
            let cull = |rule: Rule| {
                let mut blocks = whole.clone();
                let mut masks = Vec::new();
                let drawable = |t| atlas.holds(t);
                let culled = &sel.frustum_culled;
                let r = draw::cull(
                    &grid,
                    &s.cache,
                    (fv.anchor, &fv.cam),
                    (&mut blocks, culled),
                    &drawable,
                    (rule, &mut masks),
                );
                (blocks, r)
            };
            let (culled, report) = cull(Rule::Sound);
            poses += 1;
            parts += whole.len() * all.count_ones() as usize;
            if report.skipped.is_some() {
                continue;
            }
            culled_poses += 1;
            hidden += report.hidden_parts;
            assert_eq!(whole.len() - culled.len(), report.hidden, "{name} pose {i}: blocks hidden whole are not drawn");
            let (a_px, _) = renderer.render(&atlas, &fv, &whole).unwrap();
            let (b_px, _) = renderer.render(&atlas, &fv, &culled).unwrap();
            let differing = a_px.chunks(4).zip(b_px.chunks(4)).filter(|(a, b)| a != b).count();
            assert_eq!(
                differing, 0,
                "{name} pose {i}: {} parts hidden changed {differing} pixels",
                report.hidden_parts
            );
            for (k, rule) in [Rule::OccluderTop, Rule::PartBottom].into_iter().enumerate() {
                let (mutated, _) = cull(rule);
                let (c_px, _) = renderer.render(&atlas, &fv, &mutated).unwrap();
                caught[k] += usize::from(c_px != a_px);
            }
        }
    }
    eprintln!(
        "occlusion over tiles: {hidden} of {parts} parts hidden at {culled_poses} of {poses} poses culled; \
         mutations caught at {caught:?} poses"
    );
    assert!(culled_poses * 2 > poses, "culling ran at {culled_poses} of {poses} poses");
    assert!(hidden * 10 > parts, "{hidden} of {parts} parts hidden: the poses test little");
    assert!(caught.iter().all(|&c| c >= 5), "mutations changed too few frames: {caught:?}");
    common::finish(device);
}

/// The paper's error mode over the atlas (eqs. 2-4, SPEC 4 and 8): with every tile held,
/// a generation's per-block errors (each tile's blocks one LOD coarser than it, the top
/// tile's every coarser LOD, nested over the finer levels on the CPU) are the in-memory
/// reference's (`lod::gie`, which the in-memory errors activity matches) block for block
/// at three views; the selection takes them (the same blocks as in memory's paper
/// selection, morph off); a readback corrupted to a quarter selects fewer blocks.
/// For blocks of the paper's k = 33 and of the smallest and largest k a tile takes.
#[test]
fn paper_errors_over_the_atlas_are_the_in_memory_ones() {
    let hf = common::rough();
    let dir = TempDir::new("gpu-stream-paper");
    let archive = common::archive_of(&hf, &dir);
    let device = common::gpu();
    for k in [33, 9, 129] {
        paper_errors_match(&hf, &archive, &device, k);
    }
    common::finish(device);
}

fn paper_errors_match(hf: &Heightfield, archive: &Arc<Archive>, device: &Arc<Device>, k: u32) {
    use vkterrain::lod::gie::{block_errors, group_errors, ErrorMode, ErrorParams};
    use vkterrain::lod::traversal::{traverse, BlockCaches, LodSelect};
    use vkterrain::stream::traverse::StreamedLod;
    let mm = vkterrain::lod::pyramid::MinMaxPyramid::build(hf);
    let layout = vkterrain::lod::block::BlockLayout::of(hf, k).unwrap();
    let grid = Grid::from_meta(&archive.meta).with_block(k).unwrap();
    let mut s = Streamer::new(archive.clone(), grid, 1 << 30);
    let atlas = HeightAtlas::new(device, &grid, 64 << 20).unwrap();
    s.attach(Box::new(atlas.feed()), HeightAtlas::cache_tiles(atlas.layer_count()));
    s.morph = None;
    // Every tile held: full resolution seen from high above.
    let (wx, wz) = hf.world_extent();
    let centre = DVec3::new(f64::from(wx) / 2.0, 0.0, f64::from(wz) / 2.0);
    s.lod = StreamedLod::Full;
    settled(&mut s, &View::look_at(centre + DVec3::new(0.0, 20000.0, 1.0), centre, 60.0, 320, 240, 1.0));
    assert_eq!(s.cache.len(), 16 + 4 + 1, "every tile held");
    s.lod = StreamedLod::Error;
    s.error_mode = ErrorMode::Paper;
    let (mut compared, mut worst, mut blocks) = (0usize, 0.0f64, Vec::new());
    // And high above, where only blocks coarser than the top tile's level are drawn
    // (a review found them settled on the summaries' bound, no generation asked for).
    let high = View::look_at(centre + DVec3::new(0.0, 9000.0, 1.0), centre, 60.0, 320, 240, 1.0);
    for (i, view) in views().iter().chain([&high]).enumerate() {
        let sel = settled_with_errors(&mut s, view);
        let errors = atlas.feed().errors().expect("a generation");
        assert_eq!((errors.mode, errors.position), (ErrorMode::Paper, view.position), "k {k}, pose {i}");
        let cam = view.absolute();
        let want = block_errors(&group_errors(hf, &mm, &ErrorParams::new(&cam, ErrorMode::Paper)), layout.m);
        let lods = layout.root_lod();
        assert_eq!(errors.paper.len(), (0..lods).map(|j| 1 << (2 * j)).sum::<usize>(), "k {k}, pose {i}: every block");
        for (&(lod, bx, bz), &(got, whole)) in &errors.paper {
            assert!(whole, "k {k}, pose {i}: every tile held, block {lod} ({bx}, {bz}) not whole");
            let w = f64::from(want.get(lod, bx as usize, bz as usize));
            let rel = (f64::from(got) - w).abs() / w.max(1e-6);
            assert!(rel < 1e-3, "k {k}, pose {i}: block {lod} ({bx}, {bz}): {got} against {w}");
            worst = worst.max(rel);
            compared += 1;
        }
        // The blocks the in-memory paper selection draws.
        let select = LodSelect::errors(&want, cam.position, 1.0, ErrorMode::Paper).with_morph(false);
        let mem = traverse(hf, &mm, &BlockCaches::default(), &layout, &cam, select);
        let key = |l: u32, x: u32, z: u32| (l, x, z);
        let mut ours: Vec<_> = sel.blocks.iter().map(|b| key(b.lod, b.bx, b.bz)).collect();
        let mut theirs: Vec<_> = mem.blocks.iter().chain(&mem.occluded).map(|b| key(b.lod, b.bx, b.bz)).collect();
        ours.sort();
        theirs.sort();
        assert_eq!(ours, theirs, "k {k}, pose {i}: the selections differ");
        assert!(sel.errors_from_gpu > 0 && sel.errors_from_tiles == 0, "k {k}, pose {i}: {sel:?}");
        blocks.push(sel.blocks.len());
    }
    eprintln!(
        "k {k}: {compared} paper block errors compared, worst relative difference {worst:.2e}; blocks {blocks:?}"
    );
    // Corrupted to a quarter: never more blocks, fewer in all.
    atlas.corrupt_errors(0.25);
    let corrupted: Vec<usize> = views().iter().map(|view| settled_with_errors(&mut s, view).blocks.len()).collect();
    assert!(corrupted.iter().zip(&blocks).all(|(c, b)| c <= b), "{corrupted:?} corrupted, {blocks:?} not");
    assert!(corrupted.iter().sum::<usize>() < blocks.iter().sum(), "{corrupted:?} corrupted, {blocks:?} not");
    assert_eq!(atlas.failure(), None);
}

/// `errors --dump` over tiles writes the in-memory dump's layout: in the paper's mode the
/// same values as the file's own dump in memory (Puget Sound 1k, one camera), for every
/// block the view's generation shaded with every level under it (the others hold NaN).
#[test]
fn an_errors_dump_over_tiles_is_the_files_in_the_paper_mode() {
    let dir = TempDir::new("gpu-stream-dump");
    let ps = common::data("puget_sound/ps_height_1k.png");
    let dump = |tiles: bool| {
        let path = dir.path().join(if tiles { "tiles.f32" } else { "memory.f32" });
        let mut args = vec!["errors", ps.to_str().unwrap(), "--error-mode", "paper", "--validation", "on"];
        args.extend(["--camera", "60000,4000,150000", "--look-at", "80000,0,60000", "--dump", path.to_str().unwrap()]);
        if tiles {
            args.push("--stream");
        }
        let o = cli(&args);
        assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
        let bytes = std::fs::read(&path).unwrap();
        bytes.chunks_exact(4).map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]])).collect::<Vec<f32>>()
    };
    let (memory, tiles) = (dump(false), dump(true));
    assert_eq!(memory.len(), tiles.len());
    let shaded: Vec<(f32, f32)> =
        tiles.iter().zip(&memory).filter(|(t, _)| !t.is_nan()).map(|(&t, &m)| (t, m)).collect();
    assert!(shaded.len() * 4 > tiles.len(), "{} of {} blocks shaded", shaded.len(), tiles.len());
    for (i, &(t, m)) in shaded.iter().enumerate() {
        assert!((t - m).abs() <= 1e-5 * m.abs().max(1e-6), "block {i}: {t} over tiles, {m} in memory");
    }
}

/// A budget for tiles (`--cache-mb`, `--gpu-mb`) draws a file that fits one image from
/// its tiles, as `--stream` does: given, it is honoured, not noted and ignored.
#[test]
fn a_budget_for_tiles_draws_a_file_from_them() {
    let dir = TempDir::new("gpu-stream-budget");
    let ps = common::data("puget_sound/ps_height_1k.png");
    let png = dir.path().join("r.png");
    for (budget, streamed) in [(None, false), (Some("--cache-mb"), true), (Some("--gpu-mb"), true)] {
        let mut args = vec!["render", ps.to_str().unwrap(), "--size", "96x64", "--validation", "on"];
        args.extend(["--out", png.to_str().unwrap()]);
        args.extend(budget.iter().flat_map(|b| [*b, "64"]));
        let o = cli(&args);
        assert!(o.status.success(), "{budget:?}: {}", String::from_utf8_lossy(&o.stderr));
        let r: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
        assert_eq!(r["streamed"].as_bool().unwrap_or(false), streamed, "{budget:?}: {r}");
    }
}

/// Ray-cast blocks over tiles (SPEC 10), the in-memory crack check on terrains drawn from
/// their tiles: blocks drawn by rays (every other eligible block, then all of them) leave
/// no pixel showing the background where the all-raster frame shows terrain, at low views
/// over Puget Sound 1k and over knife-edge ridges and a cliff, morphing and not; the
/// images agree up to rasterization rules. A camera under the surface, or beyond the
/// terrain's edge lower than its top, casts nothing (it would see through the culled
/// undersides). Every run is validation-clean.
#[test]
fn raycast_blocks_over_tiles_leave_no_cracks() {
    let dir = TempDir::new("stream-raycast");
    let ridges = dir.path().join("ridges.png");
    image::ImageBuffer::from_fn(257, 257, |x, z| {
        let knife = if (x + 2 * z) % 23 == 0 { 25.0 } else { 0.0 };
        let cliff = if x > 150 { 40.0 } else { 0.0 };
        let h: f32 = knife + cliff + (x as f32 * 0.05).sin() * 3.0 + (z as f32 * 0.11).cos() * 2.0 + 5.0;
        image::Luma([(h * 100.0) as u16])
    })
    .save(&ridges)
    .unwrap();
    let ps = common::data("puget_sound/ps_height_1k.png");
    let ridge_frame = ["--spacing", "1", "--height-scale", "0.01"];
    let terrains: [(&std::path::Path, &[&str], [&str; 3]); 2] = [
        (
            ps.as_path(),
            &[],
            ["30000,900,30000:90000,0,90000", "150000,1500,20000:60000,0,120000", "80000,2500,140000:20000,0,60000"],
        ),
        (ridges.as_path(), &ridge_frame, ["10,30,10:200,5,200", "250,50,30:20,0,220", "128,80,128:200,0,10"]),
    ];
    let render = |file: &std::path::Path, frame: &[&str], pose: &str, extra: &[&str], name: &str| {
        let (camera, look_at) = pose.split_once(':').unwrap();
        let png = dir.path().join(format!("{name}.png"));
        let args = [
            &["render", file.to_str().unwrap(), "--stream", "--size", "320x240", "--background", "1,0,1"][..],
            frame,
            &["--camera", camera, "--look-at", look_at, "--validation", "on", "--out", png.to_str().unwrap()],
            extra,
        ]
        .concat();
        let o = cli(&args);
        assert!(o.status.success(), "{args:?}: {}", String::from_utf8_lossy(&o.stderr));
        let json = common::json_in(&String::from_utf8_lossy(&o.stdout));
        assert_eq!(json["validation_messages"], 0, "{args:?}");
        (image::open(&png).unwrap().to_rgba8().into_raw(), json["raycast_blocks"].as_u64().unwrap())
    };
    let (mut cast_blocks, mut frames, mut worst) = (0, 0, (0.0f64, 0.0f64));
    for (file, frame, poses) in terrains {
        for pose in poses {
            for morph in ["off", "on"] {
                let (raster, none) = render(file, frame, pose, &["--morph", morph], "raster");
                assert_eq!(none, 0);
                for raycast in ["checkerboard", "all"] {
                    let (cast, n) = render(file, frame, pose, &["--morph", morph, "--raycast", raycast], "cast");
                    cast_blocks += n;
                    frames += 1;
                    let magenta = |p: &[u8]| p[..3] == [255, 0, 255];
                    let holes = raster.chunks(4).zip(cast.chunks(4)).filter(|(r, c)| !magenta(r) && magenta(c)).count();
                    assert_eq!(holes, 0, "{file:?} {pose} morph {morph} {raycast}: background through ray-cast blocks");
                    // As in memory: silhouettes move by a pixel where the ray-caster's
                    // lift and the rasterizer's snapping differ.
                    let (rmse, share) = image_difference(&raster, &cast);
                    worst = (worst.0.max(rmse), worst.1.max(share));
                    assert!(rmse < 10.0 && share <= 0.01, "{file:?} {pose} {raycast}: RMSE {rmse}, share {share}");
                }
            }
        }
    }
    println!("{frames} frames, {cast_blocks} blocks ray-cast; worst RMSE {:.2}, share {:.4}", worst.0, worst.1);
    assert!(cast_blocks > 100, "only {cast_blocks} blocks were ray-cast");
    // Under the cliff's top, and beyond the east edge lower than the top: nothing cast.
    for pose in ["200,20,128:250,20,140", "300,30,128:128,20,128"] {
        let (_, n) = render(&ridges, &ridge_frame, pose, &["--morph", "off", "--raycast", "all"], "under");
        assert_eq!(n, 0, "{pose}: ray-cast blocks seen from below the surface");
    }
}
