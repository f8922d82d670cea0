//! Stopping on a signal: `calibconv train` sent SIGUSR1 mid-run finishes its step, writes its
//! checkpoint, records the segment and exits with status 75; resuming gives the weights of an
//! uninterrupted run, bit for bit. The emitted SLURM script passes the signal on to its task
//! and requeues the task on status 75 alone (run with stand-ins for `srun` and `scontrol`).
//!
//! Nothing here waits for a time: the tests wait for files a process writes (a log row, a
//! "ready" file) and then signal it.

use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::Duration;

use calibconv::experiment::layout::{RunDir, SegmentEnd};
use calibconv::experiment::profile::Profile;
use calibconv::experiment::slurm::{emit_slurm, SlurmSpec};
use calibconv::experiment::sweep::{self, Seeds};
use calibconv::train::checkpoint::read_info;
use calibconv::train::stop::INTERRUPTED_EXIT;

use crate::common::experiment::ExperimentFile;
use crate::common::{assert_contains, calibconv_command, calibconv_in, ok};

/// Steps of the interrupted run: far more than happen between its first log row and the signal
/// (the test fails, rather than passing vacuously, if the run ends before the signal).
const STEPS: i64 = 200;

/// How often the tests look for the file they wait on.
const POLL: Duration = Duration::from_millis(20);

/// A toy run of `STEPS` steps of the tiny U-Net on 16x16 images, logging every step,
/// checkpointing every 50, in `dir/runs/NAME`.
fn toy(dir: &Path, name: &str) -> PathBuf {
    ExperimentFile::tiny(name)
        .set_path("output", &dir.join("runs"))
        .set("train.steps", STEPS)
        .set("train.log_every", 1)
        .set("train.checkpoint_every", 50)
        .set_toml("data.train", r#"{ toy = 8, split = "train" }"#)
        .write(&dir.join(format!("{name}.toml")))
}

/// Waits until `ready` holds, or `child` ended (then panics with its output).
fn wait_for(child: &mut Child, ready: impl Fn() -> bool) {
    while !ready() {
        if let Some(status) = child.try_wait().unwrap() {
            panic!("the process ended ({status}) before it was ready");
        }
        std::thread::sleep(POLL);
    }
}

/// Sends `signal` to process `pid`.
fn signal(pid: u32, signal: i32) {
    // SAFETY: kill has no memory preconditions.
    assert_eq!(unsafe { libc::kill(pid as i32, signal) }, 0);
}

fn weights(path: &Path) -> Vec<(String, tch::Tensor)> {
    let mut v = tch::Tensor::read_safetensors(path).unwrap();
    v.sort_by(|a, b| a.0.cmp(&b.0));
    v
}

#[test]
fn sigusr1_stops_after_the_step_with_a_checkpoint_and_resuming_matches_an_uninterrupted_run() {
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path();
    let file = toy(dir, "stopped");
    let f = file.to_str().unwrap();
    let run = RunDir::new(dir.join("runs/stopped"));
    let mut child = calibconv_command(&["train", f, "-q"])
        .current_dir(dir)
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    // A few steps logged: training is under way.
    let csv = run.train_csv();
    wait_for(&mut child, || {
        std::fs::read_to_string(&csv).is_ok_and(|t| t.lines().count() > 3)
    });
    signal(child.id(), libc::SIGUSR1);
    let out = child.wait_with_output().unwrap();
    let err = String::from_utf8_lossy(&out.stderr);
    assert_eq!(
        out.status.code(),
        Some(i32::from(INTERRUPTED_EXIT)),
        "{err}"
    );
    assert_contains(&err, &["stopped by SIGUSR1 at step", "last.safetensors"]);
    // The checkpoint holds the step it stopped at (not a multiple of 50 in general: written on
    // the signal), before the end; no summary, so the sweep would resume it.
    let step = read_info(&run.last_checkpoint()).unwrap().unwrap().step;
    assert!((1..STEPS as u64).contains(&step), "step {step}");
    assert!(!run.summary_json().exists());
    let seg = run.read_run().unwrap().segments;
    assert_eq!(seg.len(), 1);
    assert_eq!(seg[0].reason, Some(SegmentEnd::Interrupted));
    assert_eq!((seg[0].first_step, seg[0].last_step), (0, Some(step)));
    assert!(seg[0].message.as_deref().unwrap().contains("SIGUSR1"));

    ok(calibconv_in(dir, &["train", f, "--resume", "-q"]));
    let seg = run.read_run().unwrap().segments;
    assert_eq!(seg.len(), 2);
    assert_eq!(seg[1].reason, Some(SegmentEnd::Complete));
    assert_eq!(
        (seg[1].first_step, seg[1].last_step),
        (step, Some(STEPS as u64))
    );

    // The same experiment without a stop, in another folder (same name, same seed).
    let other = dir.join("uninterrupted");
    std::fs::create_dir_all(&other).unwrap();
    let file2 = toy(&other, "stopped");
    ok(calibconv_in(
        &other,
        &["train", file2.to_str().unwrap(), "-q"],
    ));
    let a = weights(&run.last_checkpoint());
    let b = weights(&RunDir::new(other.join("runs/stopped")).last_checkpoint());
    assert_eq!(a.len(), b.len());
    for ((na, ta), (nb, tb)) in a.iter().zip(&b) {
        assert_eq!(na, nb);
        assert!(ta.equal(tb), "{na} differs from the uninterrupted run");
    }
}

/// Stand-ins for SLURM's commands: `srun` behaves as calibconv would by `$FAKE` (`stop`: exit
/// 75; `fail`: exit 1; `signal`: wait for SIGUSR1, then exit 75), `scontrol` logs its arguments.
fn stand_ins(bin: &Path) {
    std::fs::create_dir_all(bin).unwrap();
    let srun = r#"#!/bin/bash
case "$FAKE" in
  stop) exit 75 ;;
  fail) exit 1 ;;
  signal)
    trap 'echo "task got USR1" >> "$LOG"; exit 75' USR1
    touch "$READY"
    while :; do sleep 0.05; done ;;
esac
"#;
    let scontrol = "#!/bin/bash\necho \"scontrol $*\" >> \"$LOG\"\n";
    for (name, text) in [("srun", srun), ("scontrol", scontrol)] {
        let p = bin.join(name);
        std::fs::write(&p, text).unwrap();
        use std::os::unix::fs::PermissionsExt;
        std::fs::set_permissions(&p, std::fs::Permissions::from_mode(0o755)).unwrap();
    }
}

#[test]
fn the_emitted_script_passes_signals_on_and_requeues_on_status_75_only() {
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path();
    let exps = dir.join("exps");
    std::fs::create_dir_all(&exps).unwrap();
    ExperimentFile::tiny("bl")
        .set_toml("data.train", r#"{ toy = 4, split = "train" }"#)
        .write(&exps.join("bl.toml"));
    let profile = Profile::default();
    let plan = sweep::plan(&exps, &profile, &[], &[]).unwrap();
    let spec = SlurmSpec::resolve(&profile, &["signal_seconds=90".parse().unwrap()]).unwrap();
    let out = dir.join("slurm");
    emit_slurm(
        &plan,
        &exps,
        &profile,
        &[],
        &Seeds::default(),
        &[],
        &spec,
        &out,
    )
    .unwrap();
    let script = out.join("level-0.sbatch");
    let text = std::fs::read_to_string(&script).unwrap();
    assert_contains(
        &text,
        &[
            "#SBATCH --signal=B:USR1@90\n",
            "#SBATCH --requeue\n",
            "#SBATCH --open-mode=append\n",
        ],
    );
    // The traps come first: a signal before them would end the shell.
    let trap = text.find("trap 'pass_on USR1' USR1").unwrap();
    assert!(trap < text.find("\ncd ").unwrap(), "{text}");
    let submit = std::fs::read_to_string(out.join("submit.sh")).unwrap();
    assert_contains(&submit, &["watch with: ", " --status"]);

    let bin = dir.join("bin");
    stand_ins(&bin);
    let log = dir.join("log");
    let ready = dir.join("ready");
    let run = |fake: &str| -> Child {
        let _ = std::fs::remove_file(&log);
        Command::new("bash")
            .arg(&script)
            .env(
                "PATH",
                format!("{}:{}", bin.display(), std::env::var("PATH").unwrap()),
            )
            .env("FAKE", fake)
            .env("LOG", &log)
            .env("READY", &ready)
            .env("SLURM_ARRAY_JOB_ID", "12")
            .env("SLURM_ARRAY_TASK_ID", "0")
            .stdout(Stdio::piped())
            .spawn()
            .unwrap()
    };
    let logged = || std::fs::read_to_string(&log).unwrap_or_default();

    // Status 75: the task requeues itself.
    let status = run("stop").wait().unwrap();
    assert_eq!(status.code(), Some(75));
    assert_eq!(logged(), "scontrol requeue 12_0\n");

    // Any other failure: not requeued.
    let status = run("fail").wait().unwrap();
    assert_eq!(status.code(), Some(1));
    assert_eq!(logged(), "");

    // SLURM's warning reaches the batch shell only (`B:`): it passes it on to the task.
    let mut child = run("signal");
    wait_for(&mut child, || ready.exists());
    signal(child.id(), libc::SIGUSR1);
    let status = child.wait().unwrap();
    assert_eq!(status.code(), Some(75));
    assert_eq!(logged(), "task got USR1\nscontrol requeue 12_0\n");
}
