//! The draw thread's one frame step, used by `view`, `bench` and `render` alike: take the
//! newest finished error generation (asking for a new one when it pays), select the blocks,
//! submit them. One copy, so that the bench measures what the viewer does.
//!
//! Its state is explicit: the error feed, the traversal's caches, and the previous frame's
//! selection, which the next request is judged by ([`LastSelection`]).

use crate::errors::activity::ErrorsActivity;
use crate::errors::feed::{ErrorFeed, LastSelection};
use crate::lod::block::{hide_parts_outside, BlockLayout, DrawBlock, Traversal, TraversalPool};
use crate::lod::camera::Camera;
use crate::lod::heightfield::Heightfield;
use crate::lod::occlusion;
use crate::lod::pyramid::MinMaxPyramid;
use crate::lod::traversal::{traverse, BlockCaches, LodSelect, DISTANCE_FACTOR};
use crate::trace::{Trace, DRAW_TID};
use serde_json::json;
use std::time::Instant;

/// Frames the draw thread keeps in flight (viewer and bench alike).
pub const FRAMES_IN_FLIGHT: usize = 2;

/// How block LODs are chosen (`--lod`).
#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum)]
pub enum LodChoice {
    /// The paper's method: GPU error pyramid, refine while the error exceeds delta.
    Error,
    /// Every block at full resolution (brute force; the reference image).
    Full,
    /// Distance rings (GeoMipMapping-style baseline).
    Distance,
}

/// The terrain as the traversal reads it: samples, camera-independent pyramids, blocks.
#[derive(Clone, Copy)]
pub struct LodTerrain<'a> {
    pub hf: &'a Heightfield,
    pub mm: &'a MinMaxPyramid,
    pub layout: &'a BlockLayout,
}

/// What one frame is asked to draw.
pub struct FrameRequest<'a> {
    pub frame: u64,
    pub cam: &'a Camera,
    pub lod: LodChoice,
    pub delta: f32,
    /// Draw these blocks instead of traversing (the bench's ceiling run, the viewer's
    /// frozen selection); the error feed still runs when there is an activity.
    pub blocks: Option<&'a [DrawBlock]>,
}

/// What one frame did.
pub struct Frame<R> {
    /// The generation newly taken before this frame, if any.
    pub taken: Option<u64>,
    /// Milliseconds in the error feed (the first frame waits for its generation there).
    pub feed_ms: f64,
    /// The traversal, when the frame traversed (its blocks are the ones drawn).
    pub traversal: Option<Traversal>,
    pub traverse_ms: f64,
    /// The blocks the request brought, when it did not traverse.
    given: Vec<DrawBlock>,
    /// What the submission returned.
    pub submitted: R,
}

impl<R> Frame<R> {
    /// The blocks drawn.
    pub fn blocks(&self) -> &[DrawBlock] {
        self.traversal.as_ref().map_or(&self.given, |t| &t.blocks)
    }

    /// The blocks drawn and what the submission returned, moved out of the frame (no
    /// copy of the blocks).
    pub fn into_parts(self) -> (Vec<DrawBlock>, R) {
        (self.traversal.map_or(self.given, |t| t.blocks), self.submitted)
    }
}

/// The draw thread's state between frames.
pub struct DrawThread {
    pub feed: ErrorFeed,
    /// Geomorphing between LODs (`--morph`, the viewer's N key).
    pub morph: bool,
    /// Occlusion culling (`--occlusion`, the viewer's C key): hidden blocks are not drawn.
    pub occlusion: bool,
    /// When the frames' sweep runs (it pauses where it does not pay).
    probe: occlusion::Probe,
    caches: BlockCaches,
    last: LastSelection,
    trace: Trace,
    /// The traversal's worker threads (none: the draw thread alone).
    pool: TraversalPool,
}

/// Threads for the traversal's per-block work: `asked`, else 1 on a CPU device (lavapipe:
/// its rasterizer threads already keep every core busy, and even one pool worker beside
/// them slowed the fly path's traversal from 1.9 to 3.2 ms a frame: docs/benchmarks.md,
/// "On a GPU"), else every core.
pub fn traversal_threads(asked: Option<u16>, device_type: ash::vk::PhysicalDeviceType) -> usize {
    match asked {
        Some(n) => n as usize,
        None if device_type == ash::vk::PhysicalDeviceType::CPU => 1,
        None => std::thread::available_parallelism().map_or(1, |n| n.get()),
    }
}

impl DrawThread {
    pub fn new(feed: ErrorFeed, morph: bool, trace: Trace) -> Self {
        DrawThread {
            feed: feed.with_trace(trace.clone()),
            morph,
            occlusion: false,
            probe: Default::default(),
            caches: BlockCaches::default(),
            last: LastSelection::default(),
            trace,
            pool: TraversalPool::default(),
        }
    }

    /// Runs the traversal's per-block work on `threads` threads of its own (1: on the
    /// draw thread itself, with no pool).
    pub fn set_threads(&mut self, threads: usize) -> anyhow::Result<()> {
        self.pool = TraversalPool::new(threads).map_err(|e| anyhow::anyhow!(e))?;
        Ok(())
    }

    /// A finished frame's statistics: what a triangle costs the GPU, which decides
    /// whether the occlusion sweep pays ([`occlusion::Probe`]).
    pub fn observe(&mut self, done: &crate::draw::blocks::DrawStats) {
        self.probe.observe(done.gpu_ms, done.triangles);
    }

    /// The same thread with occlusion culling on or off.
    pub fn with_occlusion(mut self, on: bool) -> Self {
        self.occlusion = on;
        self
    }

    /// The selection rule for a `--lod` choice with the data in use (distance LOD until
    /// there is data).
    pub fn select(&self, lod: LodChoice, delta: f32) -> LodSelect<'_> {
        match (lod, self.feed.usable()) {
            (LodChoice::Error, Some(g)) => {
                LodSelect::errors(&g.errors, g.params.camera, delta, g.params.mode).with_morph(self.morph)
            }
            (LodChoice::Error, None) | (LodChoice::Distance, _) => LodSelect::Distance { factor: DISTANCE_FACTOR },
            (LodChoice::Full, _) => LodSelect::Full,
        }
    }

    /// Traverses with this thread's caches, outside a frame (the bench's reference runs).
    pub fn traverse(&self, terrain: LodTerrain, cam: &Camera, select: LodSelect) -> Traversal {
        self.pool.install(|| traverse(terrain.hf, terrain.mm, &self.caches, terrain.layout, cam, select))
    }

    /// One frame: the error feed (when there is an activity), the block selection (unless
    /// the request brings its blocks), then `submit` with the blocks to draw.
    pub fn step<R>(
        &mut self,
        activity: Option<&ErrorsActivity>,
        terrain: LodTerrain,
        req: FrameRequest,
        submit: impl FnOnce(&[DrawBlock]) -> anyhow::Result<R>,
    ) -> anyhow::Result<Frame<R>> {
        let started = Instant::now();
        let taken = match activity {
            Some(a) => {
                let taken = self.feed.update(a, req.cam, req.frame, self.last)?;
                self.trace.complete(DRAW_TID, "error feed", started, Instant::now(), json!({"frame": req.frame}));
                taken
            }
            None => None,
        };
        let feed_ms = started.elapsed().as_secs_f64() * 1e3;
        let t = Instant::now();
        let (traversal, given) = match req.blocks {
            Some(b) => (None, b.to_vec()),
            None => {
                let mut tr = self.traverse(terrain, req.cam, self.select(req.lod, req.delta));
                if self.occlusion {
                    self.probe.cull(terrain.hf, terrain.mm, &self.caches, terrain.layout, req.cam, &mut tr);
                }
                hide_parts_outside(terrain.hf, terrain.mm, terrain.layout, req.cam, &mut tr);
                let hidden = tr.occlusion.map(|o| (o.hidden, o.hidden_parts));
                let args = json!({"blocks": tr.blocks.len(), "morphing": tr.morphing,
                    "occluded": hidden.map(|h| h.0), "occluded_parts": hidden.map(|h| h.1),
                    "parts_outside": tr.frustum_parts});
                self.trace.complete(DRAW_TID, "traverse", t, Instant::now(), args);
                self.last = LastSelection::of(&tr);
                (Some(tr), Vec::new())
            }
        };
        let traverse_ms = t.elapsed().as_secs_f64() * 1e3;
        let submitted = submit(traversal.as_ref().map_or(&given, |t| &t.blocks))?;
        Ok(Frame { taken, feed_ms, traversal, traverse_ms, given, submitted })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::errors::feed::RefreshPolicy;
    use crate::lod::gie::ErrorMode;

    /// The step traverses unless given blocks, hands `submit` exactly the blocks it
    /// reports, and keeps what the next request is judged by: the last traversal's
    /// selection, untouched by a frame that brought its own blocks.
    #[test]
    fn one_step_selects_submits_and_remembers_the_selection() {
        let hf = crate::input::procedural::procedural_sized(129);
        let mm = MinMaxPyramid::build(&hf);
        let layout = BlockLayout::of(&hf, 9).unwrap();
        let terrain = LodTerrain { hf: &hf, mm: &mm, layout: &layout };
        let (wx, wz) = hf.world_extent();
        let cam = Camera::look_at(
            glam::Vec3::new(wx * 0.5, wx * 0.2, wz * 1.1),
            glam::Vec3::new(wx * 0.5, 0.0, wz * 0.5),
            60.0,
            320,
            240,
            crate::lod::view::near_plane(&hf),
        );
        let mut draw = DrawThread::new(ErrorFeed::new(ErrorMode::Strict, RefreshPolicy::default()), true, Trace::off());
        assert_eq!(draw.last, LastSelection::default());
        let req = FrameRequest { frame: 0, cam: &cam, lod: LodChoice::Distance, delta: 1.0, blocks: None };
        let f = draw.step(None, terrain, req, |b| Ok(b.to_vec())).unwrap();
        assert_eq!(f.blocks(), &f.submitted[..]);
        let t = f.traversal.expect("traversed");
        assert!(!t.blocks.is_empty());
        assert_eq!(f.submitted, t.blocks);
        assert_eq!(draw.last, LastSelection::of(&t));
        assert!(draw.last.nearest.is_some());
        let given = [t.blocks[0]];
        let req = FrameRequest { frame: 1, cam: &cam, lod: LodChoice::Full, delta: 1.0, blocks: Some(&given) };
        let f = draw.step(None, terrain, req, |b| Ok(b.len())).unwrap();
        assert!(f.traversal.is_none());
        assert_eq!(f.submitted, 1);
        assert_eq!(f.into_parts(), (given.to_vec(), 1));
        assert_eq!(draw.last, LastSelection::of(&t), "a frame with given blocks leaves the selection as it was");
        let full = draw.traverse(terrain, &cam, draw.select(LodChoice::Full, 1.0));
        assert!(full.blocks.iter().all(|b| b.lod == 0));
        assert!(full.blocks.len() > t.blocks.len());
    }
}
