//! The errors activity (SPEC section 4, seed 000 section 3.2): its own thread and queue,
//! fragment-shader passes only ([`crate::errors::passes`]: about `4^n / 3` fragments per
//! generation, only the block-error pyramid read back). Two slots (error images + readback buffers) are used in turn, by the rules of
//! [`crate::errors::handoff`], so that up to two generations are in flight; a timeline semaphore
//! whose value is the generation number hands each finished one to the draw thread.

use crate::errors::handoff::{Handoff, Read};
use crate::errors::passes::{readback_bytes, ErrorsGpu, MAX_PARTS};
use crate::gpu::terrain::TerrainGpu;
use crate::lod::block::BlockLayout;
use crate::lod::gie::{fragments_per_update, BlockErrors, ErrorParams};
use crate::lod::heightfield::Heightfield;
use crate::trace::{Trace, ERRORS_TID};
use crate::vk::{vk, Buffer, Device, TimelineSemaphore, VkError, VkResult, VkResultExt};
use std::collections::VecDeque;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Arc, Condvar, Mutex};
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

/// One finished generation, copied out of its readback buffer.
#[derive(Clone, Debug)]
pub struct Generation {
    pub number: u64,
    pub params: ErrorParams,
    pub errors: BlockErrors,
    /// GPU time of this update (timestamp queries), when the device has timestamps.
    pub gpu_ms: Option<f64>,
}

/// Per-update costs, for stats.
#[derive(Clone, Copy, Debug)]
pub struct UpdateCost {
    pub fragments_shaded: u64,
    pub readback_bytes: u64,
    pub levels: u32,
}

#[derive(Clone, Copy, Debug)]
struct SlotInfo {
    generation: u64,
    params: ErrorParams,
    /// The generation's GPU time, read by the errors thread once it finished: reading
    /// query results can wait for the whole queue on some drivers (lavapipe), which
    /// must not stall the draw thread.
    gpu_ms: Option<f64>,
}

/// The hand-off protocol and what each slot holds, under one lock.
struct HandoffState {
    protocol: Handoff,
    slots: [Option<SlotInfo>; 2],
}

struct Request {
    params: Option<ErrorParams>,
    stop: bool,
}

struct Shared {
    request: Mutex<Request>,
    handoff: Mutex<HandoffState>,
    /// Host events for the errors thread, counted: a new request, a released slot, stop.
    /// (A host-signalled timeline semaphore would let one wait cover the GPU too, but
    /// the validation layers of Debian bookworm time out on those: VVL issue 4649.)
    events: Mutex<u64>,
    events_cv: Condvar,
    /// Notified (with `handoff`) when a generation is published or the thread fails.
    published: Condvar,
    /// Generation `g` is written when this reaches `g`.
    timeline: TimelineSemaphore,
    /// Counts the errors queue's submissions as they complete (each signals one more).
    submissions: TimelineSemaphore,
    /// Each submission waits (on the CPU) for the one before to complete, so that at most
    /// one submission of error work sits ahead of a draw on a shared queue.
    paced: bool,
    readbacks: [Buffer; 2],
    /// The reader's copy of the newest generation it took.
    copy: Mutex<Option<Generation>>,
    failure: Mutex<Option<VkError>>,
    root_lod: u32,
    roots: [usize; 2],
    /// True while the thread waits with nothing to do.
    idle: AtomicBool,
    /// The host events the thread had seen when it last found nothing to do.
    idle_seen: AtomicU64,
    /// Most generations in flight on the GPU at once.
    most_in_flight: AtomicU64,
    /// Test hook: fail with ERROR_DEVICE_LOST when this generation is submitted (0: never).
    inject_device_lost_at: AtomicU64,
    trace: Trace,
}

impl Shared {
    /// Host events so far. Read before looking at the shared state, then wait for more:
    /// an event that comes in between is not missed.
    fn seen(&self) -> u64 {
        *self.events.lock().unwrap()
    }

    /// Wakes the errors thread if it waits for host events.
    fn notify(&self) {
        *self.events.lock().unwrap() += 1;
        self.events_cv.notify_all();
    }
}

/// How the errors thread paces its submissions (`--error-pacing`).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, clap::ValueEnum)]
pub enum Pacing {
    /// Paced exactly when the queue is shared with the draw thread.
    #[default]
    Auto,
    /// Each submission waits for the one before: draws interleave on a shared queue, and
    /// a second generation only queues once the first is done.
    Paced,
    /// Submissions go as soon as they are recorded: two generations in flight on the
    /// errors queue (the separate-queue behaviour, asked for on a shared queue).
    Free,
}

impl Pacing {
    /// Whether each submission waits for the one before, on a device whose queues are
    /// arranged as `queues`.
    pub fn paced(self, queues: crate::vk::QueueMode) -> bool {
        match self {
            Pacing::Auto => queues == crate::vk::QueueMode::Shared,
            Pacing::Paced => true,
            Pacing::Free => false,
        }
    }
}

/// Handle held by the draw thread.
pub struct ErrorsActivity {
    shared: Arc<Shared>,
    thread: Option<JoinHandle<()>>,
    pub cost: UpdateCost,
}

impl ErrorsActivity {
    /// Starts the errors thread. Nothing is computed until [`ErrorsActivity::request`].
    pub fn start(
        device: &Arc<Device>,
        terrain: Arc<TerrainGpu>,
        hf: Arc<Heightfield>,
        block_layout: BlockLayout,
    ) -> VkResult<Self> {
        Self::start_with(device, terrain, hf, block_layout, Trace::off(), Pacing::Auto)
    }

    /// Like [`ErrorsActivity::start`], recording the thread's work into `trace`, with the
    /// submissions paced as asked.
    pub fn start_with(
        device: &Arc<Device>,
        terrain: Arc<TerrainGpu>,
        hf: Arc<Heightfield>,
        block_layout: BlockLayout,
        trace: Trace,
        pacing: Pacing,
    ) -> VkResult<Self> {
        let root = block_layout.root_lod();
        let bytes = readback_bytes(&block_layout);
        let rb = |i: usize| {
            Buffer::new(
                device,
                &format!("block-error readback {i}"),
                bytes,
                vk::BufferUsageFlags::TRANSFER_DST,
                gpu_allocator::MemoryLocation::GpuToCpu,
            )
        };
        let paced = pacing.paced(device.queue_mode);
        let shared = Arc::new(Shared {
            request: Mutex::new(Request { params: None, stop: false }),
            handoff: Mutex::new(HandoffState { protocol: Handoff::default(), slots: [None, None] }),
            events: Mutex::new(0),
            events_cv: Condvar::new(),
            published: Condvar::new(),
            timeline: TimelineSemaphore::new(device, 0)?,
            submissions: TimelineSemaphore::new(device, 0)?,
            paced,
            readbacks: [rb(0)?, rb(1)?],
            copy: Mutex::new(None),
            failure: Mutex::new(None),
            root_lod: root,
            roots: block_layout.roots,
            idle: AtomicBool::new(true),
            idle_seen: AtomicU64::new(0),
            most_in_flight: AtomicU64::new(0),
            inject_device_lost_at: AtomicU64::new(0),
            trace,
        });
        let cost = UpdateCost {
            fragments_shaded: fragments_per_update(hf.n, block_layout.m, hf.roots),
            readback_bytes: bytes,
            levels: hf.n,
        };
        // The GPU objects are created here so that set-up errors reach the caller; the
        // thread then owns them (and its own command pool) exclusively.
        let gpu = ErrorsGpu::new(device, terrain, hf, block_layout)?.with_timestamps()?;
        let thread_shared = shared.clone();
        let thread = std::thread::Builder::new()
            .name("errors-activity".into())
            .spawn(move || {
                if let Err(e) = run(gpu, &thread_shared) {
                    *thread_shared.failure.lock().unwrap() =
                        Some(VkError::Thread { stage: "errors activity".into(), cause: Box::new(e) });
                    thread_shared.published.notify_all();
                }
            })
            .map_err(|e| VkError::Setup(format!("cannot start the errors thread: {e}")))?;
        Ok(ErrorsActivity { shared, thread: Some(thread), cost })
    }

    /// Asks for a generation computed with `params`; does nothing if the latest request
    /// already has them (a camera standing still starts no work).
    pub fn request(&self, params: ErrorParams) {
        let changed = {
            let mut r = self.shared.request.lock().unwrap();
            let changed = r.params != Some(params);
            r.params = Some(params);
            changed
        };
        if changed {
            self.shared.notify();
        }
    }

    /// The errors thread's failure, if it failed.
    pub fn check_failure(&self) -> VkResult<()> {
        match &*self.shared.failure.lock().unwrap() {
            Some(e) => Err(e.clone()),
            None => Ok(()),
        }
    }

    /// The newest finished generation newer than `after`, copied out; never blocks on
    /// the GPU (the errors thread publishes a generation once the GPU signalled it).
    pub fn latest(&self, after: u64) -> VkResult<Option<Generation>> {
        self.check_failure()?;
        let s = &self.shared;
        // One reader at a time: the lock is held across the copy.
        let mut copy = s.copy.lock().unwrap();
        let (g, slot, info) = {
            let mut h = s.handoff.lock().unwrap();
            match h.protocol.begin_read() {
                Read::Nothing => return Ok(None),
                Read::Copied(g) => {
                    return Ok(copy.as_ref().filter(|c| c.number == g && g > after).cloned());
                }
                Read::Copy { generation, slot } => (generation, slot, h.slots[slot]),
            }
        };
        if g <= after {
            // Published after the caller's own copy? Cannot be, but keep the slot free.
            s.handoff.lock().unwrap().protocol.end_read(g, false);
            s.notify();
            return Ok(None);
        }
        let bytes = s.readbacks[slot].mapped();
        let read = bytes.map(|bytes| {
            let len = BlockErrors::packed_len(s.root_lod, s.roots);
            let header = u32::from_le_bytes(bytes[0..4].try_into().unwrap());
            let data: Vec<f32> = bytemuck::pod_collect_to_vec(&bytes[4..4 + len * 4]);
            let trailer = u32::from_le_bytes(bytes[4 + len * 4..8 + len * 4].try_into().unwrap());
            (header, data, trailer)
        });
        let info = info.filter(|i| i.generation == g);
        let taken = match (read, info) {
            (Ok((header, data, trailer)), Some(info)) if header == g as u32 && trailer == g as u32 => Ok(Generation {
                number: g,
                params: info.params,
                errors: BlockErrors::from_packed(s.root_lod, s.roots, &data),
                gpu_ms: info.gpu_ms,
            }),
            (Err(e), _) => Err(e),
            (Ok((header, _, trailer)), _) => Err(VkError::Setup(format!(
                "hand-off broken: generation {g} read as header {header}, trailer {trailer}"
            ))),
        };
        s.handoff.lock().unwrap().protocol.end_read(g, taken.is_ok());
        // The writer may be waiting for this slot.
        s.notify();
        let taken = taken?;
        *copy = Some(taken.clone());
        Ok(Some(taken))
    }

    /// Requests `params` and blocks until a generation computed with them is finished.
    pub fn wait_for(&self, params: ErrorParams, timeout: Duration) -> VkResult<Generation> {
        // A NaN never equals itself: such a request could never be answered.
        if !(params.camera.is_finite() && params.kappa.is_finite() && params.near.is_finite()) {
            return Err(VkError::Setup(format!("error data requested for a non-finite camera {}", params.camera)));
        }
        self.request(params);
        let start = Instant::now();
        let mut after = 0;
        loop {
            if let Some(g) = self.latest(after)? {
                if g.params == params {
                    return Ok(g);
                }
                after = g.number;
            }
            if start.elapsed() > timeout {
                return Err(VkError::Setup(format!(
                    "errors activity produced no generation for this camera within {:.0} s",
                    timeout.as_secs_f64()
                )));
            }
            let h = self.shared.handoff.lock().unwrap();
            if h.protocol.finished() <= after {
                // Woken when the next one is published (or the thread failed).
                drop(self.shared.published.wait_timeout(h, Duration::from_millis(50)).unwrap());
            }
        }
    }

    /// Test hook: the errors thread fails as if the device were lost when it is about to
    /// submit generation `g`.
    pub fn inject_device_lost_at(&self, g: u64) {
        self.shared.inject_device_lost_at.store(g, Ordering::SeqCst);
    }

    /// Whether the thread has work (a request with new parameters, or a generation in
    /// flight), and its submissions completed: a watchdog's view of its progress. Counted
    /// per submission, not per generation: on a shared queue each of a generation's
    /// parts waits behind the frames queued before it, which with `--lod full` on a large
    /// terrain take seconds each. (A lost device reads as no progress.)
    pub fn progress(&self) -> (bool, u64) {
        let done = self.shared.submissions.value().unwrap_or(u64::MAX);
        (!self.shared.idle.load(Ordering::SeqCst), done)
    }

    /// True once the thread has looked at every request made so far and found nothing
    /// to do (no new parameters, nothing in flight): what "a request started no work"
    /// is checked with, instead of a sleep.
    pub fn settled(&self) -> bool {
        let events = self.shared.seen();
        self.shared.idle.load(Ordering::SeqCst) && self.shared.idle_seen.load(Ordering::SeqCst) >= events
    }

    /// Waits until [`Self::settled`]: every request made so far answered and nothing in
    /// flight. Fails if the thread failed, or after `timeout` without settling.
    pub fn wait_settled(&self, timeout: Duration) -> VkResult<()> {
        let start = Instant::now();
        while !self.settled() {
            self.check_failure()?;
            if start.elapsed() > timeout {
                return Err(VkError::Setup(format!("errors activity still busy after {:.0} s", timeout.as_secs_f64())));
            }
            // Woken when a generation is published; the timeout catches the thread going
            // idle after that, which wakes no one.
            let h = self.shared.handoff.lock().unwrap();
            drop(self.shared.published.wait_timeout(h, Duration::from_millis(5)).unwrap());
        }
        self.check_failure()
    }

    /// Whether each submission waits for the one before (`--error-pacing`).
    pub fn paced(&self) -> bool {
        self.shared.paced
    }

    /// Generations started so far (recorded; some may still be in flight).
    pub fn started(&self) -> u64 {
        self.shared.handoff.lock().unwrap().protocol.started()
    }

    /// Most generations that were in flight on the GPU at once (1 when paced; 2 when
    /// requests come faster than updates on a separate queue).
    pub fn most_in_flight(&self) -> u64 {
        self.shared.most_in_flight.load(Ordering::SeqCst)
    }

    /// The generation counter (timeline value).
    pub fn counter(&self) -> VkResult<u64> {
        self.shared.timeline.value()
    }

    /// Stops and joins the errors thread; reports its failure if it had one.
    pub fn stop(mut self) -> VkResult<()> {
        self.shutdown();
        self.check_failure()
    }

    fn shutdown(&mut self) {
        self.shared.request.lock().unwrap().stop = true;
        self.shared.notify();
        if let Some(t) = self.thread.take() {
            let _ = t.join();
        }
    }
}

impl Drop for ErrorsActivity {
    fn drop(&mut self) {
        self.shutdown();
    }
}

/// A generation recorded and not yet published.
struct InFlight {
    g: u64,
    slot: usize,
    cmds: Vec<vk::CommandBuffer>,
    /// Submissions made so far.
    submitted: usize,
    /// The value on `Shared::submissions` that its last submission signals, once made.
    last_signal: u64,
    started: Instant,
}

impl InFlight {
    fn all_submitted(&self) -> bool {
        self.submitted == self.cmds.len()
    }
}

/// The errors thread. Whatever ends it, the GPU is done with its objects before they are
/// dropped.
fn run(gpu: ErrorsGpu, s: &Shared) -> VkResult<()> {
    let mut submissions = 0u64;
    let result = event_loop(&gpu, s, &mut submissions);
    if submissions > 0 {
        // A lost device answers at once; a hung one is given 10 s.
        let _ = s.submissions.wait(submissions, 10_000_000_000);
    }
    result
}

/// The errors thread's loop over the request, the hand-off and the GPU: it publishes
/// what the GPU finished, submits the next part of a generation when pacing lets it go,
/// starts a generation for new parameters when the hand-off has a slot for it, and
/// otherwise sleeps until the GPU or the host (a request, a released slot, stop) wakes
/// it. `submissions` is the value the last submission signals on `s.submissions`.
fn event_loop(gpu: &ErrorsGpu, s: &Shared, submissions: &mut u64) -> VkResult<()> {
    let mut flight: VecDeque<InFlight> = VecDeque::new();
    // Parameters of the newest generation started.
    let mut last: Option<ErrorParams> = None;
    // Submissions the next generation is split into, from the last one's GPU time.
    let mut parts = FIRST_PARTS;
    loop {
        // Read before looking at the shared state, so that no event in between is missed.
        let seen = s.seen();
        // Submissions complete in order; a generation is done when its last one is.
        let completed = s.submissions.value()?;
        while flight.front().is_some_and(|f| f.all_submitted() && f.last_signal <= completed) {
            if let Some(ms) = publish(gpu, s, &flight.pop_front().expect("front"))? {
                parts = parts_for(ms);
            }
        }
        let (stop, params) = {
            let r = s.request.lock().unwrap();
            (r.stop, r.params)
        };
        if stop {
            return Ok(());
        }
        let fresh = params.filter(|p| Some(*p) != last);
        let queue_ready = !s.paced || completed >= *submissions;
        if let Some(next) = flight.iter().position(|f| !f.all_submitted()) {
            if queue_ready {
                if flight[next].submitted == 0 {
                    // Generations on the GPU once this one is: the earlier ones whose
                    // last submission has not completed, and this one.
                    let earlier = flight.iter().take(next).filter(|e| e.last_signal > completed).count();
                    s.most_in_flight.fetch_max(1 + earlier as u64, Ordering::SeqCst);
                }
                let f = &mut flight[next];
                submit_next(gpu, s, f, submissions)?;
                continue;
            }
        } else if let Some(p) = fresh {
            let started = {
                let mut h = s.handoff.lock().unwrap();
                h.protocol.can_start().then(|| {
                    let g = h.protocol.start();
                    let info = SlotInfo { generation: g, params: p, gpu_ms: None };
                    h.slots[Handoff::slot(g)] = Some(info);
                    g
                })
            };
            if let Some(g) = started {
                s.idle.store(false, Ordering::SeqCst);
                if s.inject_device_lost_at.load(Ordering::SeqCst) == g {
                    return Err(vk::Result::ERROR_DEVICE_LOST)
                        .vk("vkQueueSubmit2 (injected fault)")
                        .map_err(|e| VkError::Thread { stage: format!("generation {g}"), cause: Box::new(e) });
                }
                let slot = Handoff::slot(g);
                let begun = Instant::now();
                let cmds = gpu.record(slot, g, &p, &s.readbacks[slot], None, parts)?;
                flight.push_back(InFlight { g, slot, cmds, submitted: 0, last_signal: 0, started: begun });
                last = Some(p);
                continue;
            }
        }
        // Nothing to do now: sleep until the GPU or the host has news.
        let nothing = flight.is_empty() && fresh.is_none();
        if nothing {
            s.idle_seen.store(seen, Ordering::SeqCst);
        }
        s.idle.store(nothing, Ordering::SeqCst);
        if flight.is_empty() {
            let events = s.events.lock().unwrap();
            if *events == seen {
                // The timeout only bounds the damage of a lost wake-up.
                drop(s.events_cv.wait_timeout(events, Duration::from_millis(100)).unwrap());
            }
        } else {
            // GPU work in flight: wait for the first completion that matters (the oldest
            // generation's last submission, or the submission the next one paces on).
            // One semaphore: lavapipe's wait for any of several spins on a core. Unpaced,
            // look at host events every 2 ms meanwhile (a request that can start a
            // second generation, a released slot); paced, nothing can be submitted
            // before this completes anyway.
            let next = match flight.front() {
                Some(f) if f.all_submitted() => f.last_signal,
                _ => *submissions,
            };
            s.submissions.wait(next, if s.paced { 100_000_000 } else { HOST_LOOK_NS })?;
        }
    }
}

/// How often the unpaced errors thread looks at host events while it waits for the GPU
/// (over tiles too).
pub(crate) const HOST_LOOK_NS: u64 = 2_000_000;

/// Submits `f`'s next command buffer. Each submission signals one more on
/// `s.submissions`; the last also signals generation `f.g` on the timeline.
fn submit_next(gpu: &ErrorsGpu, s: &Shared, f: &mut InFlight, submissions: &mut u64) -> VkResult<()> {
    let last = f.submitted + 1 == f.cmds.len();
    *submissions += 1;
    if last {
        f.last_signal = *submissions;
    }
    let cmds = [vk::CommandBufferSubmitInfo::default().command_buffer(f.cmds[f.submitted])];
    let all = vk::PipelineStageFlags2::ALL_COMMANDS;
    let mut signal =
        vec![vk::SemaphoreSubmitInfo::default().semaphore(s.submissions.handle).value(*submissions).stage_mask(all)];
    if last {
        signal.push(vk::SemaphoreSubmitInfo::default().semaphore(s.timeline.handle).value(f.g).stage_mask(all));
    }
    let submit = [vk::SubmitInfo2::default().command_buffer_infos(&cmds).signal_semaphore_infos(&signal)];
    let (asked, got) = gpu.device.errors_queue.submit_timed(&gpu.device, &submit, vk::Fence::null())?;
    s.trace.complete(ERRORS_TID, "wait (queue lock)", asked, got, serde_json::json!({"generation": f.g}));
    f.submitted += 1;
    if last {
        s.trace.instant(
            ERRORS_TID,
            "submit (errors queue)",
            serde_json::json!({"generation": f.g, "signals": f.g, "submissions": f.cmds.len()}),
        );
    }
    Ok(())
}

/// Submissions a generation is split into before any has been timed.
const FIRST_PARTS: usize = 4;
/// GPU time of one submission the split aims at (ms). On a shared queue a frame can be
/// delayed by one submission, so this bounds the delay; more parts make a generation
/// wait behind more frames (each part waits for the one before), so data gets older.
/// On lavapipe the 1k flyover's 9 ms generations go in 2 parts, the 4k flyover's 130 ms
/// in [`MAX_PARTS`]; on a real GPU a generation is one submission.
const PART_MS: f64 = 6.0;

/// Submissions for a generation like the last one, which took `ms` on the GPU.
fn parts_for(ms: f64) -> usize {
    if !ms.is_finite() {
        return FIRST_PARTS;
    }
    ((ms / PART_MS).ceil() as usize).clamp(1, MAX_PARTS)
}

/// Generation `f.g` is done on the GPU: reads its GPU time (returned) and hands it to
/// the reader.
fn publish(gpu: &ErrorsGpu, s: &Shared, f: &InFlight) -> VkResult<Option<f64>> {
    // The generation's GPU time (sum over its submissions) and GPU spans; the slot's
    // queries are not reset before g + 2 starts, which needs g published.
    let shared = gpu.device.queue_mode == crate::vk::QueueMode::Shared;
    let mut gpu_ms = None;
    if let (Some(q), Some(buf)) = (&gpu.queries, gpu.timestamps.get(f.slot)) {
        let ticks: Vec<u64> = bytemuck::pod_collect_to_vec(&buf.mapped()?[..f.cmds.len() * 16]);
        let mut sum = 0.0;
        for (c, t) in ticks.chunks(2).enumerate() {
            sum += q.ms([t[0], t[1]]);
            let args = serde_json::json!({"generation": f.g, "submission": c});
            s.trace.gpu_span(s.trace.gpu_tid(true, shared), "error passes", [t[0], t[1]], args);
        }
        gpu_ms = Some(sum);
    }
    // Traced before the reader can see it, so that the hand-off arrow never points back.
    if s.trace.enabled() {
        s.trace.flow(ERRORS_TID, true, f.g);
    }
    s.trace.complete(
        ERRORS_TID,
        "generation",
        f.started,
        Instant::now(),
        serde_json::json!({"generation": f.g, "slot": f.slot}),
    );
    s.trace.counter("errors timeline (signalled)", f.g);
    {
        let mut h = s.handoff.lock().unwrap();
        if let Some(info) = h.slots[f.slot].as_mut() {
            info.gpu_ms = gpu_ms;
        }
        h.protocol.finish(f.g);
        s.published.notify_all();
    }
    Ok(gpu_ms)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Parts follow the last generation's GPU time, at most `MAX_PARTS`, at least 1.
    #[test]
    fn a_generation_is_split_by_the_last_ones_gpu_time() {
        assert_eq!(parts_for(0.0), 1);
        assert_eq!(parts_for(0.4), 1);
        assert_eq!(parts_for(PART_MS), 1);
        assert_eq!(parts_for(PART_MS + 0.1), 2);
        assert_eq!(parts_for(9.0), 2);
        assert_eq!(parts_for(130.0), MAX_PARTS);
        assert_eq!(parts_for(f64::NAN), FIRST_PARTS);
        assert_eq!(parts_for(f64::INFINITY), FIRST_PARTS);
    }
}
