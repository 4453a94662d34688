//! Chrome trace-event recording (opens in Perfetto or chrome://tracing): both threads'
//! work, every queue submission, every timeline-semaphore value signalled and observed.

use serde_json::{json, Value};
use std::sync::{Arc, Mutex};
use std::time::Instant;

/// Thread ids in the trace.
pub const DRAW_TID: u32 = 1;
pub const ERRORS_TID: u32 = 2;

/// A cheap handle; `Trace::off()` records nothing.
#[derive(Clone)]
pub struct Trace {
    events: Option<Arc<Mutex<Vec<Value>>>>,
    origin: Instant,
}

impl Trace {
    pub fn off() -> Self {
        Trace { events: None, origin: Instant::now() }
    }

    pub fn on() -> Self {
        let t = Trace { events: Some(Arc::new(Mutex::new(Vec::new()))), origin: Instant::now() };
        t.push(json!({"ph": "M", "pid": 1, "tid": DRAW_TID, "name": "thread_name", "args": {"name": "blocks rendering (draw thread)"}}));
        t.push(
            json!({"ph": "M", "pid": 1, "tid": ERRORS_TID, "name": "thread_name", "args": {"name": "errors activity"}}),
        );
        t
    }

    pub fn enabled(&self) -> bool {
        self.events.is_some()
    }

    fn us(&self, at: Instant) -> f64 {
        at.saturating_duration_since(self.origin).as_secs_f64() * 1e6
    }

    fn push(&self, v: Value) {
        if let Some(e) = &self.events {
            e.lock().unwrap().push(v);
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

    pub fn write(&self, path: &std::path::Path) -> std::io::Result<()> {
        let events = self.events.as_ref().map(|e| e.lock().unwrap().clone()).unwrap_or_default();
        let doc = json!({"traceEvents": events, "displayTimeUnit": "ms"});
        std::fs::write(path, serde_json::to_vec(&doc)?)
    }
}
