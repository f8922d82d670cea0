//! The run-directory lock across processes: while `calibconv train` trains a run, a second
//! `calibconv train` or `calibconv eval` of it fails at once with an error naming the first
//! one's PID; after `kill -9` of the holder the lock is free again (the OS releases it).

use std::path::Path;
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

use calibconv::experiment::layout::RunDir;

use crate::common;
use crate::common::experiment::ExperimentFile;

/// How long the holder may take to start training and write its first checkpoint (a loaded
/// 2-core machine builds the binary's libtorch state in a few seconds).
const START_TIMEOUT: Duration = Duration::from_secs(120);
/// "At once": a refused process exits well before it could have built a network.
const REFUSAL_TIMEOUT: Duration = Duration::from_secs(20);

/// A toy experiment that trains for as long as it is let, with a checkpoint every 2 steps.
fn experiment(dir: &Path) -> ExperimentFile {
    ExperimentFile::tiny("locked")
        .set_path("output", &dir.join("runs"))
        .set_toml("data.train", r#"{ toy = 8, split = "train" }"#)
        .set_toml("data.test", r#"{ toy = 4, split = "test" }"#)
        .set("train.steps", 100000000)
        .set("train.checkpoint_every", 2)
}

/// The binary with `args`, on one OpenMP thread.
fn calibconv(args: &[&str]) -> Command {
    let mut c = common::calibconv_command(args);
    c.env("OMP_NUM_THREADS", "1");
    c
}

#[test]
fn a_second_process_is_refused_naming_the_holder_and_kill_9_leaves_no_stale_lock() {
    let tmp = tempfile::tempdir().unwrap();
    let file = experiment(tmp.path()).write(&tmp.path().join("locked.toml"));
    let f = file.display().to_string();
    let run = RunDir::new(tmp.path().join("runs/locked"));

    let mut holder = calibconv(&["train", &f, "-q"])
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .spawn()
        .unwrap();
    let pid = holder.id();
    let start = Instant::now();
    loop {
        let locked_by_it =
            std::fs::read_to_string(run.lock_file()).is_ok_and(|t| t.trim() == pid.to_string());
        if locked_by_it && run.last_checkpoint().is_file() {
            break;
        }
        assert!(
            holder.try_wait().unwrap().is_none(),
            "the training process ended early"
        );
        assert!(start.elapsed() < START_TIMEOUT, "no checkpoint yet");
        std::thread::sleep(Duration::from_millis(100));
    }

    for cmd in ["train", "eval"] {
        let t = Instant::now();
        let o = calibconv(&[cmd, &f, "-q"]).output().unwrap();
        let err = common::stderr(&o);
        assert!(!o.status.success(), "{cmd}: {err}");
        let holder = format!("in use by process {pid}");
        assert!(err.contains(&holder), "{cmd}: {err}");
        assert!(
            t.elapsed() < REFUSAL_TIMEOUT,
            "{cmd} took {:?}",
            t.elapsed()
        );
    }

    holder.kill().unwrap(); // SIGKILL
    holder.wait().unwrap();
    // The lock file still names the dead process; the lock itself is gone.
    assert_eq!(
        std::fs::read_to_string(run.lock_file()).unwrap().trim(),
        pid.to_string()
    );
    common::ok(calibconv(&["eval", &f, "-q"]).output().unwrap());
    assert!(run.metrics_json("test").is_file());
}
