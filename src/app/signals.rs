//! Stop requests from signals: Ctrl-C (SIGINT), SIGTERM (a `timeout`, a service manager)
//! and SIGHUP (a closed terminal). A long run polls [`Stop::flag`] and cleans up; a run
//! that exits on one exits with the code a shell expects, 128 + the signal (130, 143, 129).
//! A second signal ends the run at once with that code.

use std::sync::atomic::{AtomicBool, AtomicUsize, Ordering};
use std::sync::Arc;

const SIGNALS: [i32; 3] = [signal_hook::consts::SIGINT, signal_hook::consts::SIGTERM, signal_hook::consts::SIGHUP];

pub struct Stop {
    requested: Arc<AtomicBool>,
    /// The last signal that arrived (0: none).
    signal: Arc<AtomicUsize>,
}

impl Stop {
    /// Installs the handlers. A failure to install one (not expected on Linux) leaves that
    /// signal's default action, which ends the run without cleaning up: printed, not fatal.
    pub fn install() -> Stop {
        let stop = Stop { requested: Arc::new(AtomicBool::new(false)), signal: Arc::new(AtomicUsize::new(0)) };
        for sig in SIGNALS {
            // A second signal ends the process at once (128 + the signal): a stop that
            // waits on something stuck (a read from a stalled server) never traps the
            // user. Registered first, so that the first signal finds the flag unset.
            let installed = signal_hook::flag::register_conditional_shutdown(sig, 128 + sig, stop.requested.clone())
                .and_then(|_| signal_hook::flag::register_usize(sig, stop.signal.clone(), sig as usize))
                .and_then(|_| signal_hook::flag::register(sig, stop.requested.clone()));
            if let Err(e) = installed {
                eprintln!("vkterrain: note: signal {sig} keeps its default action ({e})");
            }
        }
        stop
    }

    /// Set once a stop signal arrived (what the long loops poll).
    pub fn flag(&self) -> &Arc<AtomicBool> {
        &self.requested
    }

    pub fn requested(&self) -> bool {
        self.requested.load(Ordering::SeqCst)
    }

    /// 128 + the signal that arrived (130 when none has: a stop asked for otherwise).
    pub fn exit_code(&self) -> i32 {
        match self.signal.load(Ordering::SeqCst) {
            0 => 130,
            sig => 128 + sig as i32,
        }
    }
}
