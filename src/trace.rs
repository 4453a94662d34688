//! Chrome trace-event recording (opens in Perfetto or chrome://tracing): both threads'
//! work, every queue submission, every timeline-semaphore value signalled and observed.
//! Events are streamed to the file as they happen, so a run of hours keeps memory flat.

use serde_json::{json, Value};
use std::fs::File;
use std::io::{BufWriter, Write};
use std::path::{Path, PathBuf};
use std::sync::{Arc, Mutex};
use std::time::Instant;

/// Thread ids in the trace.
pub const DRAW_TID: u32 = 1;
pub const ERRORS_TID: u32 = 2;

struct Sink {
    out: BufWriter<File>,
    partial: PathBuf,
    path: PathBuf,
    first: bool,
    failed: Option<std::io::Error>,
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
        let sink = Sink { out, partial, path: path.to_path_buf(), first: true, failed: None };
        let t = Trace { sink: Some(Arc::new(Mutex::new(sink))), origin: Instant::now() };
        t.push(json!({"ph": "M", "pid": 1, "tid": DRAW_TID, "name": "thread_name", "args": {"name": "blocks rendering (draw thread)"}}));
        t.push(
            json!({"ph": "M", "pid": 1, "tid": ERRORS_TID, "name": "thread_name", "args": {"name": "errors activity"}}),
        );
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

    /// A counter track (timeline values).
    pub fn counter(&self, name: &str, value: u64) {
        if self.enabled() {
            self.push(
                json!({"ph": "C", "pid": 1, "name": name, "ts": self.us(Instant::now()), "args": {"value": value}}),
            );
        }
    }

    /// Closes the event list and moves the file into place.
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
