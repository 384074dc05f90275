//! Ctrl-C (SIGINT) and SIGTERM during training. The first one asks the run to stop: it
//! finishes the step under way, writes its checkpoint and exits with 128 + the signal's number
//! (130 for SIGINT, 143 for SIGTERM) and a message naming the checkpoint. A second one ends the
//! process at once, as the signal would without a handler; the checkpoint write is atomic, so
//! the checkpoint on disk is then the previous one, whole.
//!
//! The handlers come from `signal-hook`, which keeps what runs in the handler to atomic stores
//! and one `write` (both async-signal-safe) and orders several actions on one signal.

use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::Arc;

use crate::CliResult;

/// Whether a stop was asked for, and by which signal.
pub struct Interrupt {
    /// The signal's number once one came, 0 before.
    signal: Arc<AtomicUsize>,
}

/// A run stopped on request: the message says where its work is, and the process exits with
/// [`Interrupted::exit_code`].
#[derive(Debug)]
pub struct Interrupted {
    pub signal: i32,
    pub message: String,
}

impl Interrupted {
    /// 128 + the signal's number, as a shell reports a process ended by it.
    pub fn exit_code(&self) -> i32 {
        128 + self.signal
    }
}

impl std::fmt::Display for Interrupted {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(&self.message)
    }
}

impl std::error::Error for Interrupted {}

impl Interrupt {
    /// Catches SIGINT and SIGTERM for the rest of the process (a training run: the first
    /// signal stops it after its step, with its checkpoint).
    pub fn catch() -> CliResult<Interrupt> {
        Interrupt::catch_saying(
            b"\nstopping after this step to write the checkpoint (signal again to quit at once, without it)\n",
        )
    }

    /// As [`Interrupt::catch`], printing `said` when the first signal comes.
    #[cfg(unix)]
    pub fn catch_saying(said: &'static [u8]) -> CliResult<Interrupt> {
        use signal_hook::consts::{SIGINT, SIGTERM};
        use signal_hook::flag;
        use std::sync::atomic::AtomicBool;

        let caught = Arc::new(AtomicBool::new(false));
        let signal = Arc::new(AtomicUsize::new(0));
        for sig in [SIGINT, SIGTERM] {
            let failed = |e: std::io::Error| format!("cannot catch signal {sig}: {e}");
            // The actions run in this order: the second signal finds `caught` set and ends the
            // process as the signal's default would; the first prints a line and sets it.
            flag::register_conditional_default(sig, Arc::clone(&caught)).map_err(failed)?;
            // SAFETY: the action calls write(2) on a static buffer, which is async-signal-safe.
            unsafe {
                signal_hook::low_level::register(sig, move || {
                    libc::write(2, said.as_ptr().cast(), said.len());
                })
            }
            .map_err(failed)?;
            flag::register_usize(sig, Arc::clone(&signal), sig as usize).map_err(failed)?;
            flag::register(sig, Arc::clone(&caught)).map_err(failed)?;
        }
        Ok(Interrupt { signal })
    }

    #[cfg(not(unix))]
    pub fn catch_saying(_said: &'static [u8]) -> CliResult<Interrupt> {
        Ok(Interrupt::never())
    }

    /// An interrupt that never comes (the demo leaves the signals as they are).
    pub fn never() -> Interrupt {
        Interrupt { signal: Arc::new(AtomicUsize::new(0)) }
    }

    /// The signal that asked for a stop, if one did.
    pub fn requested(&self) -> Option<i32> {
        match self.signal.load(Ordering::SeqCst) {
            0 => None,
            s => Some(s as i32),
        }
    }
}

/// The signal's name ("SIGINT") or number.
pub fn signal_name(signal: i32) -> String {
    #[cfg(unix)]
    if let Some(name) = signal_hook::low_level::signal_name(signal) {
        return name.to_string();
    }
    format!("signal {signal}")
}
