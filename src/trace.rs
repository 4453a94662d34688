//! Chrome trace-event recording (opens in Perfetto or chrome://tracing): both threads'
//! work, every queue submission, every timeline-semaphore value signalled and observed.
//! Events are streamed to the file as they happen, so a run of hours keeps memory flat.

use crate::vk::GpuClock;
use serde_json::{json, Value};
use std::fs::File;
use std::io::{BufWriter, Write};
use std::path::{Path, PathBuf};
use std::sync::{Arc, Mutex};
use std::time::Instant;

/// Thread ids in the trace.
pub const DRAW_TID: u32 = 1;
pub const ERRORS_TID: u32 = 2;
/// A streamed terrain's IO thread (tile reads).
pub const IO_TID: u32 = 3;
/// GPU tracks: what each queue executed, from timestamp queries. With one shared queue
/// both activities' work is on [`GPU_DRAW_QUEUE_TID`].
pub const GPU_DRAW_QUEUE_TID: u32 = 10;
pub const GPU_ERRORS_QUEUE_TID: u32 = 11;

struct Sink {
    out: BufWriter<File>,
    partial: PathBuf,
    path: PathBuf,
    first: bool,
    failed: Option<std::io::Error>,
    gpu_clock: Option<GpuClock>,
}

/// A cheap handle; `Trace::off()` records nothing.
#[derive(Clone)]
pub struct Trace {
    sink: Option<Arc<Mutex<Sink>>>,
    origin: Instant,
}

impl Trace {
    pub fn off() -> Self {
        Trace { sink: None, origin: Instant::now() }
    }

    /// Streams into `path` (through `path.partial` until [`Trace::finish`]).
    pub fn to_file(path: &Path) -> std::io::Result<Self> {
        let partial = path.with_extension("json.partial");
        let mut out = BufWriter::new(File::create(&partial)?);
        out.write_all(b"{\"displayTimeUnit\": \"ms\", \"traceEvents\": [\n")?;
        let sink = Sink { out, partial, path: path.to_path_buf(), first: true, failed: None, gpu_clock: None };
        let t = Trace { sink: Some(Arc::new(Mutex::new(sink))), origin: Instant::now() };
        t.push(json!({"ph": "M", "pid": 1, "tid": DRAW_TID, "name": "thread_name", "args": {"name": "blocks rendering (draw thread)"}}));
        t.push(
            json!({"ph": "M", "pid": 1, "tid": ERRORS_TID, "name": "thread_name", "args": {"name": "errors activity"}}),
        );
        t.push(json!({"ph": "M", "pid": 1, "tid": IO_TID, "name": "thread_name", "args": {"name": "IO (tile reads, streamed terrains)"}}));
        Ok(t)
    }

    pub fn enabled(&self) -> bool {
        self.sink.is_some()
    }

    fn us(&self, at: Instant) -> f64 {
        at.saturating_duration_since(self.origin).as_secs_f64() * 1e6
    }

    fn push(&self, v: Value) {
        if let Some(s) = &self.sink {
            let mut s = s.lock().unwrap_or_else(|e| e.into_inner());
            if s.failed.is_some() {
                return;
            }
            let sep: &[u8] = if s.first { b"" } else { b",\n" };
            s.first = false;
            let r =
                s.out.write_all(sep).and_then(|_| serde_json::to_writer(&mut s.out, &v).map_err(std::io::Error::other));
            if let Err(e) = r {
                s.failed = Some(e);
            }
        }
    }

    /// A span of work on a thread.
    pub fn complete(&self, tid: u32, name: &str, start: Instant, end: Instant, args: Value) {
        if self.enabled() {
            let ts = self.us(start);
            self.push(json!({"ph": "X", "pid": 1, "tid": tid, "name": name, "ts": ts, "dur": self.us(end) - ts, "args": args}));
        }
    }

    /// A point event (a submission, a semaphore signal or observation).
    pub fn instant(&self, tid: u32, name: &str, args: Value) {
        if self.enabled() {
            self.push(json!({"ph": "i", "s": "t", "pid": 1, "tid": tid, "name": name, "ts": self.us(Instant::now()), "args": args}));
        }
    }

    /// Enables GPU tracks: timestamps are placed with `clock`; `shared` when both
    /// activities use one queue (one track). The method goes into the trace's metadata.
    pub fn set_gpu_clock(&self, clock: GpuClock, shared: bool) {
        let Some(s) = &self.sink else { return };
        s.lock().unwrap_or_else(|e| e.into_inner()).gpu_clock = Some(clock);
        let draw = if shared { "GPU: the shared queue (both activities)" } else { "GPU: draw queue" };
        self.push(
            json!({"ph": "M", "pid": 1, "tid": GPU_DRAW_QUEUE_TID, "name": "thread_name", "args": {"name": draw}}),
        );
        if !shared {
            self.push(json!({"ph": "M", "pid": 1, "tid": GPU_ERRORS_QUEUE_TID, "name": "thread_name", "args": {"name": "GPU: errors queue"}}));
        }
        self.push(json!({"ph": "M", "pid": 1, "name": "gpu_clock", "args": {
            "method": clock.method,
            "uncertainty_us": clock.uncertainty_us,
            "period_ns": clock.period_ns,
        }}));
    }

    /// The GPU track a queue's work goes on.
    pub fn gpu_tid(&self, errors_queue: bool, shared: bool) -> u32 {
        if errors_queue && !shared {
            GPU_ERRORS_QUEUE_TID
        } else {
            GPU_DRAW_QUEUE_TID
        }
    }

    /// A span of GPU work between two timestamps, on a GPU track.
    pub fn gpu_span(&self, tid: u32, name: &str, ticks: [u64; 2], args: Value) {
        let Some(s) = &self.sink else { return };
        let Some(c) = s.lock().unwrap_or_else(|e| e.into_inner()).gpu_clock else { return };
        let at = |t: u64| self.us(c.cpu_at) + (t as f64 - c.tick_at as f64) * c.period_ns / 1e3;
        let (ts, end) = (at(ticks[0]), at(ticks[1]));
        self.push(
            json!({"ph": "X", "pid": 1, "tid": tid, "name": name, "ts": ts, "dur": (end - ts).max(0.0), "args": args}),
        );
    }

    /// A flow arrow from now on `tid` (phase "s") or to now on `tid` (phase "f"): the
    /// generation a timeline signal made, to the frame that first uses it.
    pub fn flow(&self, tid: u32, start: bool, id: u64) {
        if self.enabled() {
            let ts = self.us(Instant::now());
            let ph = if start { "s" } else { "f" };
            self.push(json!({"ph": ph, "bp": "e", "pid": 1, "tid": tid, "name": "generation", "cat": "handoff", "id": id, "ts": ts}));
        }
    }

    /// A counter track (timeline values).
    pub fn counter(&self, name: &str, value: u64) {
        if self.enabled() {
            self.push(
                json!({"ph": "C", "pid": 1, "name": name, "ts": self.us(Instant::now()), "args": {"value": value}}),
            );
        }
    }

    /// Closes the event list and moves the file into place. A trace never finished (a
    /// run that failed or was stopped before it could say what it did) leaves no file:
    /// its partial file goes with its last handle.
    pub fn finish(&self) -> std::io::Result<()> {
        let Some(s) = &self.sink else { return Ok(()) };
        let mut s = s.lock().unwrap_or_else(|e| e.into_inner());
        if let Some(e) = s.failed.take() {
            return Err(e);
        }
        s.out.write_all(b"\n]}\n")?;
        s.out.flush()?;
        std::fs::rename(&s.partial, &s.path)
    }
}

impl Drop for Sink {
    fn drop(&mut self) {
        // Gone already once finished (moved into place).
        let _ = std::fs::remove_file(&self.partial);
    }
}
