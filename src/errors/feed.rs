//! The draw thread's view of the errors activity: what to ask it for, which finished
//! generation to draw with, how old it is. The draw thread's frame step
//! ([`crate::draw::frame`]) owns one.

use crate::errors::activity::{ErrorsActivity, Generation};
use crate::lod::block::Traversal;
use crate::lod::camera::Camera;
use crate::lod::gie::{ErrorMode, ErrorParams};
use crate::trace::{Trace, DRAW_TID};
use crate::vk::VkResult;
use glam::Vec3;
use serde_json::json;
use std::collections::VecDeque;
use std::time::{Duration, Instant};

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
    /// When the last request was made, and the GPU time of the newest update.
    requested_when: Option<Instant>,
    update_ms: Option<f64>,
    trace: Trace,
}

/// What the refresh policy reads of the frame before: how near the drawn terrain was and
/// how many blocks its traversal split for staleness alone. The draw thread passes it in
/// (nothing drawn yet: the default).
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct LastSelection {
    pub nearest: Option<f32>,
    pub stale_splits: usize,
}

impl LastSelection {
    pub fn of(t: &Traversal) -> Self {
        LastSelection { nearest: t.nearest, stale_splits: t.stale_splits }
    }
}

impl ErrorFeed {
    pub fn new(mode: ErrorMode, policy: RefreshPolicy) -> Self {
        ErrorFeed {
            mode,
            policy,
            current: None,
            requested_at: None,
            recent: VecDeque::new(),
            requested_when: None,
            update_ms: None,
            trace: Trace::off(),
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

    /// Forgets the generation in use (made for a heightfield that has changed: the
    /// viewer's vertical exaggeration): the next update waits for data at its camera.
    pub fn reset(&mut self) {
        self.current = None;
        self.requested_at = None;
    }

    /// Switches the error mode; data made for the other mode is no longer used.
    pub fn set_mode(&mut self, mode: ErrorMode) {
        if mode != self.mode {
            self.mode = mode;
            self.requested_at = None;
        }
    }

    /// Before frame `frame` at `cam`: requests a generation when it pays (judged by the
    /// camera's move and `last`, the frame before's selection), then takes the newest
    /// finished one. Until data for the current mode exists the call waits for a
    /// generation at this camera, so the bound holds from the first frame; after that it
    /// never waits. Returns the generation newly taken, if any.
    pub fn update(
        &mut self,
        activity: &ErrorsActivity,
        cam: &Camera,
        frame: u64,
        last: LastSelection,
    ) -> VkResult<Option<u64>> {
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
            if rested && self.policy.should_request(self.requested_at, cam.position, last.nearest, last.stale_splits) {
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
