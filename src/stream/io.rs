//! The IO thread (SPEC section 8, the third thread): reads and decodes the tiles the
//! traversal asks for into [`TileData`], the most wanted first. A request replaces the
//! previous one (what the camera needed a frame ago matters less than what it needs
//! now); a tile being read, or read and not yet taken, is not read again.

use super::cache::TileData;
use super::{Grid, TileKey};
use crate::input::archive::tile::Tile;
use crate::input::archive::Archive;
use std::collections::{HashSet, VecDeque};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Condvar, Mutex};

/// Where tiles come from: an archive on disk, or a test's source.
pub trait TileSource: Send + Sync {
    /// The tile and the bytes read for it; `Ok(None)` where none is stored.
    fn read(&self, key: TileKey) -> Result<Option<(Tile, u64)>, String>;
}

impl TileSource for Archive {
    fn read(&self, key: TileKey) -> Result<Option<(Tile, u64)>, String> {
        match self.read_tile_counted(key.level, key.tx, key.tz) {
            Ok((Some(tile), bytes)) => Ok(Some((tile, bytes))),
            Ok((None, _)) => Ok(None),
            Err(e) => Err(e.to_string()),
        }
    }
}

/// What the IO thread hands back for a requested tile.
#[derive(Debug)]
pub enum Loaded {
    Tile {
        data: Arc<TileData>,
        bytes_read: u64,
    },
    /// The archive stores no such tile.
    Absent(TileKey),
    /// Reading or decoding failed (a damaged tile, a file gone): the message names it.
    Failed(TileKey, String),
}

impl Loaded {
    pub fn key(&self) -> TileKey {
        match self {
            Loaded::Tile { data, .. } => data.key,
            Loaded::Absent(k) | Loaded::Failed(k, _) => *k,
        }
    }
}

#[derive(Default)]
struct State {
    queue: VecDeque<TileKey>,
    busy: Option<TileKey>,
    done: Vec<Loaded>,
    stop: bool,
}

struct Shared {
    state: Mutex<State>,
    /// Signalled when the queue gets work or the thread is stopped.
    work: Condvar,
    /// Signalled when a result is ready.
    ready: Condvar,
}

/// The IO thread; dropping it stops and joins the thread.
pub struct Io {
    shared: Arc<Shared>,
    thread: Option<std::thread::JoinHandle<()>>,
}

impl Io {
    pub fn spawn(source: Arc<dyn TileSource>, grid: Grid) -> Self {
        let shared =
            Arc::new(Shared { state: Mutex::new(State::default()), work: Condvar::new(), ready: Condvar::new() });
        let worker = shared.clone();
        let thread = std::thread::Builder::new()
            .name("io".into())
            .spawn(move || run(&worker, source.as_ref(), &grid))
            .expect("spawn the IO thread");
        Io { shared, thread: Some(thread) }
    }

    /// Replaces what is waiting to be read with `keys`, most wanted first (duplicates,
    /// the tile being read and results not yet taken are left out).
    pub fn request(&self, keys: &[TileKey]) {
        let mut s = self.shared.state.lock().expect("io state");
        let taken: HashSet<TileKey> = s.done.iter().map(Loaded::key).chain(s.busy).collect();
        let mut seen = HashSet::new();
        s.queue = keys.iter().copied().filter(|k| !taken.contains(k) && seen.insert(*k)).collect();
        if !s.queue.is_empty() {
            self.shared.work.notify_one();
        }
    }

    /// Tiles waiting or being read.
    pub fn outstanding(&self) -> usize {
        let s = self.shared.state.lock().expect("io state");
        s.queue.len() + usize::from(s.busy.is_some())
    }

    /// Results ready now (never blocks).
    pub fn arrived(&self) -> Vec<Loaded> {
        std::mem::take(&mut self.shared.state.lock().expect("io state").done)
    }

    /// Blocks until at least one result is ready or nothing is outstanding, then takes
    /// the results (for runs that wait for their tiles, and tests). With `stop`, it also
    /// returns (with what is ready, perhaps nothing) once `stop` is set: a read that hangs
    /// on a stalled server does not hold a stop request up. `stop` is looked at every
    /// 100 ms while nothing arrives (a signal handler cannot notify a condition variable).
    pub fn wait(&self, stop: Option<&AtomicBool>) -> Vec<Loaded> {
        let stopped = || stop.is_some_and(|s| s.load(Ordering::SeqCst));
        let mut s = self.shared.state.lock().expect("io state");
        while s.done.is_empty() && (s.busy.is_some() || !s.queue.is_empty()) && !stopped() {
            s = self.shared.ready.wait_timeout(s, STOP_POLL).expect("io state").0;
        }
        std::mem::take(&mut s.done)
    }
}

/// How often a wait for tiles looks at its stop flag.
const STOP_POLL: std::time::Duration = std::time::Duration::from_millis(100);

/// How long dropping the IO thread waits for its read in hand to end before leaving the
/// thread to end with the process (a read from a stalled server times out only after a
/// minute).
const JOIN_WITHIN: std::time::Duration = std::time::Duration::from_secs(2);

impl Drop for Io {
    fn drop(&mut self) {
        self.shared.state.lock().expect("io state").stop = true;
        self.shared.work.notify_all();
        if let Some(t) = self.thread.take() {
            let deadline = std::time::Instant::now() + JOIN_WITHIN;
            // Polled (a JoinHandle has no timed join): the thread sees `stop` as soon as
            // its read ends.
            while !t.is_finished() && std::time::Instant::now() < deadline {
                std::thread::sleep(std::time::Duration::from_millis(5));
            }
            if t.is_finished() {
                let _ = t.join();
            }
        }
    }
}

fn run(shared: &Shared, source: &dyn TileSource, grid: &Grid) {
    loop {
        let key = {
            let mut s = shared.state.lock().expect("io state");
            loop {
                if s.stop {
                    return;
                }
                if let Some(k) = s.queue.pop_front() {
                    s.busy = Some(k);
                    break k;
                }
                s = shared.work.wait(s).expect("io state");
            }
        };
        let loaded = match source.read(key) {
            Ok(Some((tile, bytes_read))) => match TileData::new(grid, tile) {
                Ok(data) if data.key == key => Loaded::Tile { data: Arc::new(data), bytes_read },
                Ok(data) => Loaded::Failed(key, format!("asked for {key:?}, the archive gave {:?}", data.key)),
                Err(e) => Loaded::Failed(key, e),
            },
            Ok(None) => Loaded::Absent(key),
            Err(e) => Loaded::Failed(key, e),
        };
        let mut s = shared.state.lock().expect("io state");
        s.busy = None;
        s.done.push(loaded);
        shared.ready.notify_all();
    }
}
