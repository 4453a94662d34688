//! The blocks rendering activity's CPU side, shared by `view`, `bench` and `render`: the
//! error feed (what to ask the errors activity for, which finished generation to draw
//! with, how old it is) and block selection. One copy, so that the bench measures what
//! the viewer does.

use crate::camera::Camera;
use crate::commands::LodChoice;
use crate::errors_activity::{ErrorsActivity, Generation};
use crate::gie::{ErrorMode, ErrorParams};
use crate::heightfield::{Heightfield, MinMaxPyramid};
use crate::quadtree::{traverse, BlockLayout, LodSelect, Traversal};
use crate::trace::{Trace, DRAW_TID};
use crate::vk::VkResult;
use glam::Vec3;
use serde_json::json;
use std::collections::VecDeque;
use std::time::{Duration, Instant};

/// Frames the draw thread keeps in flight (viewer and bench alike).
pub const FRAMES_IN_FLIGHT: usize = 2;

/// When the draw thread asks for new error data. Stale data keeps the bound (the
/// traversal scales a block's error by `d / (d - m)` for a camera that moved `m`), so
/// a new generation only pays once that inflation starts to cost triangles: when the
/// last traversal split blocks for staleness alone (`Traversal::stale_splits`). Where
/// every block is split on its own merit (terrain that needs full resolution), updates
/// would cost time and save nothing.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct RefreshPolicy {
    /// Request when the camera has moved this fraction of the distance to the nearest
    /// drawn terrain since the last request (0: every frame the camera moves). At 0.05
    /// the nearest blocks' errors are inflated by at most about 5 %, farther ones less.
    pub moved_fraction: f32,
    /// At most this share of wall time goes to error updates (1: no cap): after an
    /// update that took `u` ms on the GPU, the next request waits `u (1/share - 1)` ms.
    /// On a shared queue every update delays the frames behind it; the cap keeps the
    /// frame rate near the rasterizer's while the stale correction keeps the bound.
    pub max_share: f32,
}

impl Default for RefreshPolicy {
    fn default() -> Self {
        RefreshPolicy { moved_fraction: 0.05, max_share: 0.05 }
    }
}

impl RefreshPolicy {
    /// Milliseconds to leave between requests after an update of `update_ms`.
    pub fn spacing_ms(&self, update_ms: f64) -> f64 {
        if self.max_share >= 1.0 {
            0.0
        } else {
            update_ms * (1.0 / self.max_share.max(1e-3) as f64 - 1.0)
        }
    }

    /// Whether a camera at `now` should request new data, last requested at `requested`,
    /// with the nearest drawn terrain `nearest` away (None: nothing drawn yet) and
    /// `stale_splits` blocks split for staleness alone in the last traversal (ignored at
    /// `moved_fraction` 0, which asks every frame the camera moves).
    pub fn should_request(
        &self,
        requested: Option<Vec3>,
        now: Vec3,
        nearest: Option<f32>,
        stale_splits: usize,
    ) -> bool {
        match (requested, nearest) {
            (None, _) | (_, None) => true,
            (Some(r), Some(d)) => {
                let moved = (now - r).length();
                let pays = stale_splits > 0 || self.moved_fraction == 0.0;
                moved > 0.0 && moved >= self.moved_fraction * d && pays
            }
        }
    }
}

/// The draw thread's view of the errors activity.
pub struct ErrorFeed {
    mode: ErrorMode,
    policy: RefreshPolicy,
    current: Option<Generation>,
    requested_at: Option<Vec3>,
    /// Camera position per recent frame, to tell the age of the data in frames.
    recent: VecDeque<(u64, Vec3)>,
    /// Distance to the nearest drawn block in the last frame.
    nearest: Option<f32>,
    /// Blocks the last frame's traversal split for staleness alone.
    stale_splits: usize,
    /// When the last request was made, and the GPU time of the newest update.
    requested_when: Option<Instant>,
    update_ms: Option<f64>,
    trace: Trace,
    /// Geomorphing between LODs (`--morph`, the viewer's M key).
    pub morph: bool,
}

impl ErrorFeed {
    pub fn new(mode: ErrorMode, policy: RefreshPolicy) -> Self {
        ErrorFeed {
            mode,
            policy,
            current: None,
            requested_at: None,
            recent: VecDeque::new(),
            nearest: None,
            stale_splits: 0,
            requested_when: None,
            update_ms: None,
            trace: Trace::off(),
            morph: true,
        }
    }

    /// Records requests, observed generations and traversals into `trace`.
    pub fn with_trace(mut self, trace: Trace) -> Self {
        self.trace = trace;
        self
    }

    pub fn mode(&self) -> ErrorMode {
        self.mode
    }

    /// Switches the error mode; data made for the other mode is no longer used.
    pub fn set_mode(&mut self, mode: ErrorMode) {
        if mode != self.mode {
            self.mode = mode;
            self.requested_at = None;
        }
    }

    /// Before frame `frame` at `cam`: requests a generation when it pays, then takes the
    /// newest finished one. Until data for the current mode exists the call waits for a
    /// generation at this camera, so the bound holds from the first frame; after that it
    /// never waits. Returns the generation newly taken, if any.
    pub fn update(&mut self, activity: &ErrorsActivity, cam: &Camera, frame: u64) -> VkResult<Option<u64>> {
        let started = Instant::now();
        let taken = self.update_inner(activity, cam, frame)?;
        self.trace.complete(DRAW_TID, "error feed", started, Instant::now(), json!({"frame": frame}));
        Ok(taken)
    }

    fn update_inner(&mut self, activity: &ErrorsActivity, cam: &Camera, frame: u64) -> VkResult<Option<u64>> {
        let params = ErrorParams::new(cam, self.mode);
        let mut taken = None;
        if self.usable().is_none() {
            let g = activity.wait_for(params, Duration::from_secs(600))?;
            self.requested_at = Some(cam.position);
            taken = Some(g.number);
            self.update_ms = g.gpu_ms.or(self.update_ms);
            self.current = Some(g);
        } else {
            let rested = match (self.requested_when, self.update_ms) {
                (Some(t), Some(u)) => t.elapsed().as_secs_f64() * 1e3 >= self.policy.spacing_ms(u),
                _ => true,
            };
            if rested && self.policy.should_request(self.requested_at, cam.position, self.nearest, self.stale_splits) {
                activity.request(params);
                self.requested_at = Some(cam.position);
                self.requested_when = Some(Instant::now());
                self.trace.instant(DRAW_TID, "request generation", json!({"frame": frame}));
            }
            let after = self.current.as_ref().map_or(0, |g| g.number);
            if let Some(g) = activity.latest(after)? {
                taken = Some(g.number);
                self.update_ms = g.gpu_ms.or(self.update_ms);
                self.current = Some(g);
            }
        }
        self.recent.push_back((frame, cam.position));
        if self.recent.len() > 4096 {
            self.recent.pop_front();
        }
        if let Some(n) = taken {
            self.trace.flow(DRAW_TID, false, n);
            self.trace.instant(DRAW_TID, "observed generation", json!({"generation": n, "frame": frame}));
            self.trace.counter("errors timeline (observed by draw thread)", n);
        }
        Ok(taken)
    }

    /// The generation in use, if it was made for the current mode.
    pub fn usable(&self) -> Option<&Generation> {
        self.current.as_ref().filter(|g| g.params.mode == self.mode)
    }

    /// GPU time of the newest error update, when the device has timestamps.
    pub fn update_ms(&self) -> Option<f64> {
        self.update_ms
    }

    /// Frames since the camera was where the data in use was computed.
    pub fn age_frames(&self, frame: u64) -> Option<u64> {
        let g = self.usable()?;
        self.recent.iter().rev().find(|(_, c)| *c == g.params.camera).map(|(f, _)| frame - f)
    }

    /// Selects this frame's blocks with the data in use (distance LOD until there is
    /// data), and remembers how near the drawn terrain is for the refresh policy.
    pub fn traverse(
        &mut self,
        hf: &Heightfield,
        mm: &MinMaxPyramid,
        layout: &BlockLayout,
        cam: &Camera,
        delta: f32,
    ) -> Traversal {
        self.traverse_lod(LodChoice::Error, hf, mm, layout, cam, delta)
    }

    /// Selects this frame's blocks for a `--lod` choice: the error data in use, the
    /// distance baseline, or everything at full resolution.
    pub fn traverse_lod(
        &mut self,
        lod: LodChoice,
        hf: &Heightfield,
        mm: &MinMaxPyramid,
        layout: &BlockLayout,
        cam: &Camera,
        delta: f32,
    ) -> Traversal {
        let select = match (lod, self.usable()) {
            (LodChoice::Error, Some(g)) => {
                LodSelect::errors(&g.errors, g.params.camera, delta, g.params.mode).with_morph(self.morph)
            }
            (LodChoice::Error, None) | (LodChoice::Distance, _) => LodSelect::Distance { factor: 2.0 },
            (LodChoice::Full, _) => LodSelect::Full,
        };
        let started = Instant::now();
        let t = traverse(hf, mm, layout, cam, select);
        let args = json!({"blocks": t.blocks.len(), "morphing": t.morphing});
        self.trace.complete(DRAW_TID, "traverse", started, Instant::now(), args);
        self.nearest = t.nearest;
        self.stale_splits = t.stale_splits;
        t
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn refresh_waits_until_the_inflation_would_cost() {
        let p = RefreshPolicy::default();
        let at = Vec3::new(0.0, 100.0, 0.0);
        assert!(p.should_request(None, at, Some(100.0), 0), "no request yet");
        assert!(p.should_request(Some(at), at, None, 0), "nothing drawn yet");
        assert!(!p.should_request(Some(at), at, Some(100.0), 1), "standing still");
        assert!(!p.should_request(Some(at), at + Vec3::X * 4.9, Some(100.0), 1));
        assert!(p.should_request(Some(at), at + Vec3::X * 5.0, Some(100.0), 1));
        // Nothing split for staleness: new data would not save a triangle.
        assert!(!p.should_request(Some(at), at + Vec3::X * 50.0, Some(100.0), 0));
        // Close to the ground a small move already matters.
        assert!(p.should_request(Some(at), at + Vec3::X * 0.2, Some(3.0), 1));
        let every = RefreshPolicy { moved_fraction: 0.0, max_share: 1.0 };
        assert_eq!(every.spacing_ms(100.0), 0.0);
        assert!((p.spacing_ms(150.0) - 2850.0).abs() < 1e-3, "5 % of the time: 150 ms on, 2850 ms off");
        assert!(every.should_request(Some(at), at + Vec3::X * 1e-3, Some(1e6), 0));
        assert!(!every.should_request(Some(at), at, Some(1e6), 0));
    }
}
