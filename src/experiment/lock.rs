//! The lock of a run directory ([`RunLock`]) and the probe a status view uses to see who holds
//! it without getting in its way ([`RunDir::lock_holder`]).

use std::fs::{File, OpenOptions, TryLockError};
use std::io::{Read, Seek, SeekFrom, Write};
use std::path::{Path, PathBuf};

use super::layout::RunDir;
use crate::error::{Error, Result};

/// An exclusive lock on a run directory, held while a process trains or evaluates it.
///
/// It is an advisory lock (`flock`) on `RUN/lock`, which holds the holder's PID: the OS
/// releases it when the process ends, however it ends (`kill -9` included), so it never goes
/// stale; the file itself stays. A second process (or a second lock in one process) fails
/// with [`Error::Busy`] naming the holder's PID, after trying again for a moment (0.2 s: a
/// status probe holds the lock shared for an instant).
#[derive(Debug)]
pub struct RunLock {
    file: File,
    path: PathBuf,
}

impl RunLock {
    pub(super) fn acquire(run: &RunDir) -> Result<RunLock> {
        std::fs::create_dir_all(run.path()).map_err(|e| Error::io(run.path(), e))?;
        let path = run.lock_file();
        let mut file = OpenOptions::new()
            .read(true)
            .write(true)
            .create(true)
            .truncate(false)
            .open(&path)
            .map_err(|e| Error::io(&path, e))?;
        // A status view's probe ([`RunDir::lock_holder`]) holds a shared lock for an instant:
        // a busy lock is tried again for a moment before it counts as held.
        let mut tries = 0;
        let got = loop {
            match file.try_lock() {
                Err(TryLockError::WouldBlock) if tries < LOCK_TRIES => {
                    tries += 1;
                    std::thread::sleep(LOCK_RETRY_WAIT);
                }
                other => break other,
            }
        };
        match got {
            Ok(()) => {}
            Err(TryLockError::WouldBlock) => {
                let mut text = String::new();
                let _ = file.read_to_string(&mut text);
                return Err(Error::Busy {
                    path: run.path().to_path_buf(),
                    holder: text
                        .trim()
                        .parse::<u32>()
                        .map(|pid| format!("process {pid}"))
                        .unwrap_or_else(|_| "another process".into()),
                });
            }
            Err(TryLockError::Error(e)) => return Err(Error::io(&path, e)),
        }
        let pid = std::process::id();
        file.set_len(0)
            .and_then(|()| file.seek(SeekFrom::Start(0)))
            .and_then(|_| writeln!(file, "{pid}"))
            .and_then(|()| file.flush())
            .map_err(|e| Error::io(&path, e))?;
        Ok(RunLock { file, path })
    }

    /// The lock file.
    pub fn path(&self) -> &Path {
        &self.path
    }
}

/// How often [`RunLock`] tries a busy lock again, and how long it waits before each: 20 x 10
/// ms, far longer than a status probe holds it, short enough to fail "at once" for a user.
const LOCK_TRIES: u32 = 20;
const LOCK_RETRY_WAIT: std::time::Duration = std::time::Duration::from_millis(10);

impl RunDir {
    /// Who holds the run's lock: `None` when no process does, else the holder's PID as its
    /// lock file says (`None` inside if unreadable). Never writes: it tries a shared lock and
    /// releases it at once (the lock works across the machines of a shared file system that
    /// supports `flock`, which is how a login node sees a compute node's run).
    pub fn lock_holder(&self) -> Result<Option<Option<u32>>> {
        let path = self.lock_file();
        let mut file = match File::open(&path) {
            Ok(f) => f,
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(None),
            Err(e) => return Err(Error::io(&path, e)),
        };
        match file.try_lock_shared() {
            Ok(()) => {
                let _ = file.unlock();
                Ok(None)
            }
            Err(TryLockError::WouldBlock) => {
                let mut text = String::new();
                let _ = file.read_to_string(&mut text);
                Ok(Some(text.trim().parse::<u32>().ok()))
            }
            Err(TryLockError::Error(e)) => Err(Error::io(&path, e)),
        }
    }
}

impl Drop for RunLock {
    fn drop(&mut self) {
        let _ = self.file.unlock();
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_second_lock_fails_naming_the_holder_and_dropping_releases_it() {
        let tmp = tempfile::tempdir().unwrap();
        let run = RunDir::new(tmp.path().join("r"));
        let held = run.lock().unwrap();
        let e = run.lock().unwrap_err().to_string();
        assert!(
            e.contains(&format!("process {}", std::process::id())),
            "{e}"
        );
        assert_eq!(
            run.lock_holder().unwrap(),
            Some(Some(std::process::id())),
            "the probe sees the holder"
        );
        drop(held);
        assert_eq!(run.lock_holder().unwrap(), None);
        // A probe leaves the lock free for the next holder.
        run.lock().unwrap();
    }
}
