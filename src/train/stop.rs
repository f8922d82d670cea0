//! Stopping a run cleanly on a signal: SIGUSR1 (what SLURM sends before a time limit, see
//! [`crate::experiment::slurm`]), SIGTERM (preemption, `scancel`, the time limit itself) and
//! SIGINT (Ctrl-C in a terminal).
//!
//! [`install`] makes those signals set a flag instead of ending the process. The trainer reads
//! the flag once per step: when it is set, it finishes the step, writes `last.*` (atomically,
//! as every checkpoint) and returns [`Error::Interrupted`](crate::error::Error::Interrupted);
//! the binary then exits with [`INTERRUPTED_EXIT`] (75, `EX_TEMPFAIL`), which the emitted SLURM
//! scripts turn into `scontrol requeue`. A second SIGINT ends the process at once (exit status
//! 130), for a user who does not want to wait for the step; the checkpoint files are whole
//! either way, since they are replaced by rename.

use std::sync::atomic::{AtomicI32, Ordering};

/// The exit status of a process that stopped on a signal after writing its checkpoint:
/// `EX_TEMPFAIL` of sysexits.h (try again later). Nothing else exits with it.
pub const INTERRUPTED_EXIT: u8 = 75;

/// The flag the installed handlers set: the number of the first signal that asked to stop,
/// 0 while none did.
static PROCESS_FLAG: AtomicI32 = AtomicI32::new(0);

/// A stop request that the trainer polls: the process's (set by the handlers of [`install`]),
/// or one of its own (tests, or embedding code that stops runs its own way).
#[derive(Clone, Copy, Debug)]
pub struct StopFlag(&'static AtomicI32);

impl Default for StopFlag {
    /// The process's flag.
    fn default() -> Self {
        StopFlag::process()
    }
}

impl StopFlag {
    /// The flag the signal handlers set.
    pub fn process() -> StopFlag {
        StopFlag(&PROCESS_FLAG)
    }

    /// A flag of its own that no signal sets (it lives as long as the process).
    pub fn detached() -> StopFlag {
        StopFlag(Box::leak(Box::new(AtomicI32::new(0))))
    }

    /// Asks to stop, as signal `signal` (a number, e.g. `libc::SIGUSR1`) does; the first
    /// request is kept.
    pub fn request(&self, signal: i32) {
        let _ = self
            .0
            .compare_exchange(0, signal, Ordering::SeqCst, Ordering::SeqCst);
    }

    /// The signal that asked to stop, if one did.
    pub fn requested(&self) -> Option<i32> {
        match self.0.load(Ordering::SeqCst) {
            0 => None,
            s => Some(s),
        }
    }

    /// Forgets a request (a process that goes on after handling one).
    pub fn clear(&self) {
        self.0.store(0, Ordering::SeqCst);
    }
}

/// The name of a signal number: `SIGUSR1`, `SIGTERM`, `SIGINT`, else `signal N`.
pub fn signal_name(signal: i32) -> String {
    match signal {
        libc::SIGUSR1 => "SIGUSR1".into(),
        libc::SIGTERM => "SIGTERM".into(),
        libc::SIGINT => "SIGINT".into(),
        n => format!("signal {n}"),
    }
}

/// The handler: only async-signal-safe work (an atomic store; `_exit` on a second SIGINT).
extern "C" fn on_signal(signal: libc::c_int) {
    let first = PROCESS_FLAG
        .compare_exchange(0, signal, Ordering::SeqCst, Ordering::SeqCst)
        .is_ok();
    if !first && signal == libc::SIGINT {
        // SAFETY: `_exit` is async-signal-safe and takes no pointers.
        unsafe { libc::_exit(130) };
    }
}

/// Makes SIGUSR1, SIGTERM and SIGINT set the process's [`StopFlag`] (see the module docs).
/// Installing twice is harmless. Returns the OS error of a failed `sigaction`.
pub fn install() -> std::io::Result<()> {
    for signal in [libc::SIGUSR1, libc::SIGTERM, libc::SIGINT] {
        // SAFETY: a zeroed `sigaction` is a valid initial value; the handler is an
        // `extern "C" fn(c_int)` that only touches an atomic (and `_exit`); SA_RESTART keeps
        // interrupted system calls (file reads and writes) from failing with EINTR.
        let rc = unsafe {
            let mut action: libc::sigaction = std::mem::zeroed();
            action.sa_sigaction = on_signal as extern "C" fn(libc::c_int) as libc::sighandler_t;
            action.sa_flags = libc::SA_RESTART;
            libc::sigemptyset(&mut action.sa_mask);
            libc::sigaction(signal, &action, std::ptr::null_mut())
        };
        if rc != 0 {
            return Err(std::io::Error::last_os_error());
        }
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_flag_keeps_the_first_request_until_cleared() {
        let f = StopFlag::detached();
        assert_eq!(f.requested(), None);
        f.request(libc::SIGUSR1);
        f.request(libc::SIGTERM);
        assert_eq!(f.requested(), Some(libc::SIGUSR1));
        assert_eq!(signal_name(libc::SIGUSR1), "SIGUSR1");
        f.clear();
        assert_eq!(f.requested(), None);
    }
}
