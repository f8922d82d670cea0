//! Where a sweep stands (`calibconv sweep DIR --status`): one row per planned run, from its
//! run directory's records alone, so it can run on a login node while the runs train on
//! compute nodes (a shared file system) and while they write (every record is replaced by
//! rename, so a reader sees the old file or the new one, whole).
//!
//! A run is, checked in this order:
//! - **running** when a process holds its lock (probed with a shared lock that is released at
//!   once: see [`RunDir::lock_holder`]), with the holder's PID and, from the open segment of
//!   `run.json`, its host and SLURM job;
//! - **complete** when trained and every evaluation is written;
//! - **failed** when its latest segment failed, or its `sweep.json` (newer than the latest
//!   segment's start) records a failure or a block: the error's first line;
//! - **interrupted at step N** when it has a checkpoint (or a segment) but is not complete:
//!   stopped on a signal, killed, or trained with evaluations left;
//! - **not started** otherwise.
//!
//! Each row also gives the steps done (from the last checkpoint's header, or `summary.json`)
//! and when the last checkpoint was written.

use std::path::Path;
use std::time::UNIX_EPOCH;

use super::layout::{unix_now, RunDir, SegmentEnd, SweepStatus};
use super::sweep::Planned;
use crate::error::Result;
use crate::train::checkpoint;
use crate::train::Length;

/// The state of one run.
#[derive(Clone, Debug, PartialEq)]
pub enum RunState {
    /// Trained and evaluated.
    Complete,
    /// A process holds the run's lock.
    Running {
        pid: Option<u32>,
        host: Option<String>,
        slurm_job: Option<String>,
    },
    /// Stopped before it was complete; `evaluations_left`: trained, not all evaluated.
    Interrupted { evaluations_left: bool },
    /// The latest attempt failed (or was blocked): the error's first line.
    Failed(String),
    /// No record of any attempt.
    NotStarted,
}

/// One row of the status table.
#[derive(Clone, Debug, PartialEq)]
pub struct StatusRow {
    /// `seed-S/NAME`, or `NAME` without seeds.
    pub run: String,
    pub state: RunState,
    /// Steps done, and planned when the run counts steps (not epochs).
    pub steps: Option<u64>,
    pub total: Option<u64>,
    /// When `checkpoints/last.safetensors` was written (Unix seconds).
    pub last_checkpoint: Option<f64>,
}

/// The rows of `plan`, in plan order.
pub fn status(plan: &[Planned]) -> Vec<StatusRow> {
    plan.iter()
        .map(|p| {
            let evals: Vec<&str> = p.exp.evals.iter().map(|e| e.name.as_str()).collect();
            let total = match p.exp.train.length {
                Length::Steps(s) => Some(s),
                Length::Epochs(_) => None,
            };
            run_status(&RunDir::new(&p.exp.run_dir), p.key(), &evals, total)
        })
        .collect()
}

/// The row of the run directory `dir` (named `run`, with evaluations `evals` and `total`
/// steps planned). An unreadable record makes the row a failure that names it.
pub fn run_status(dir: &RunDir, run: String, evals: &[&str], total: Option<u64>) -> StatusRow {
    let last = dir.last_checkpoint();
    let mut row = StatusRow {
        run,
        state: RunState::NotStarted,
        steps: None,
        total,
        last_checkpoint: modified(&last),
    };
    if let Err(e) = fill(dir, evals, &mut row) {
        row.state = RunState::Failed(format!("unreadable record: {}", first_line(&e.to_string())));
    }
    row
}

/// Fills in the state and steps of `row`.
fn fill(dir: &RunDir, evals: &[&str], row: &mut StatusRow) -> Result<()> {
    let last = dir.last_checkpoint();
    row.steps = match checkpoint::read_info(&last) {
        Ok(info) => info.map(|i| i.step),
        Err(_) if !last.exists() => None,
        Err(e) => return Err(e),
    };
    let record = dir.run_if_any()?;
    let segment = record.as_ref().and_then(|r| r.segments.last());
    if let Some(pid) = dir.lock_holder()? {
        let open = segment.filter(|s| s.end.is_none());
        row.state = RunState::Running {
            pid,
            host: open.map(|s| s.host.clone()),
            slurm_job: open.and_then(|s| s.slurm_job.clone()),
        };
        return Ok(());
    }
    let summary = dir.summary_if_any()?;
    let evaluated = evals.iter().all(|e| dir.metrics_json(e).is_file());
    if let Some(s) = &summary {
        row.steps = Some(s.steps);
        if evaluated {
            row.state = RunState::Complete;
            return Ok(());
        }
    }
    // The latest failure: of the last segment, or of a sweep after it started.
    let mut failure = segment
        .filter(|s| s.reason == Some(SegmentEnd::Failed))
        .map(|s| s.message.clone().unwrap_or_else(|| "failed".into()));
    if let Some(sweep) = dir.sweep_if_any()? {
        let newer = match (segment, modified(&dir.sweep_json())) {
            (Some(seg), Some(t)) => t >= seg.start,
            _ => true,
        };
        let what = match sweep.status {
            SweepStatus::Failed => Some(""),
            SweepStatus::Blocked => Some("blocked: "),
            _ => None,
        };
        if let (true, Some(prefix)) = (newer, what) {
            let error = sweep.error.as_deref().unwrap_or("no message");
            failure = Some(format!("{prefix}{}", first_line(error)));
        }
    }
    row.state = if let Some(f) = failure {
        RunState::Failed(first_line(&f).to_string())
    } else if summary.is_some() || row.steps.is_some() || segment.is_some() {
        RunState::Interrupted {
            evaluations_left: summary.is_some(),
        }
    } else {
        RunState::NotStarted
    };
    Ok(())
}

/// The first line of `text`.
fn first_line(text: &str) -> &str {
    text.lines().next().unwrap_or("")
}

/// When `path` was last modified (Unix seconds), if it exists.
fn modified(path: &Path) -> Option<f64> {
    let t = std::fs::metadata(path).ok()?.modified().ok()?;
    Some(t.duration_since(UNIX_EPOCH).ok()?.as_secs_f64())
}

impl RunState {
    /// The state column: `complete`, `running (SLURM 12_3 on n1, pid 42)`, `interrupted at
    /// step 120`, `failed: ...`, `not started`.
    pub fn describe(&self, steps: Option<u64>) -> String {
        match self {
            RunState::Complete => "complete".into(),
            RunState::Running {
                pid,
                host,
                slurm_job,
            } => {
                let mut parts = Vec::new();
                if let Some(j) = slurm_job {
                    parts.push(format!("SLURM {j}"));
                }
                if let Some(p) = pid {
                    parts.push(format!("pid {p}"));
                }
                let mut s = format!("running ({})", parts.join(", "));
                if parts.is_empty() {
                    s = "running".into();
                }
                if let Some(h) = host {
                    s += &format!(" on {h}");
                }
                s
            }
            RunState::Interrupted { evaluations_left } => format!(
                "interrupted at step {}{}",
                steps.unwrap_or(0),
                if *evaluations_left {
                    " (evaluations left)"
                } else {
                    ""
                }
            ),
            RunState::Failed(e) => format!("failed: {e}"),
            RunState::NotStarted => "not started".into(),
        }
    }
}

/// `YYYY-MM-DD HH:MM UTC` of Unix seconds `t`.
fn utc(t: f64) -> String {
    let secs = t.max(0.0) as i64;
    let (days, rem) = (secs.div_euclid(86_400), secs.rem_euclid(86_400));
    // Civil date from days since 1970-01-01 (H. Hinnant's `civil_from_days`).
    let z = days + 719_468;
    let era = z.div_euclid(146_097);
    let doe = z - era * 146_097;
    let yoe = (doe - doe / 1_460 + doe / 36_524 - doe / 146_096) / 365;
    let doy = doe - (365 * yoe + yoe / 4 - yoe / 100);
    let mp = (5 * doy + 2) / 153;
    let day = doy - (153 * mp + 2) / 5 + 1;
    let month = if mp < 10 { mp + 3 } else { mp - 9 };
    let year = yoe + era * 400 + i64::from(month <= 2);
    format!(
        "{year:04}-{month:02}-{day:02} {:02}:{:02} UTC",
        rem / 3600,
        rem % 3600 / 60
    )
}

/// How long ago `t` was, seen at `now`: `42 s`, `7 min`, `3.5 h`, `2.0 d`.
fn ago(t: f64, now: f64) -> String {
    let d = (now - t).max(0.0);
    if d < 60.0 {
        format!("{d:.0} s ago")
    } else if d < 3600.0 {
        format!("{:.0} min ago", d / 60.0)
    } else if d < 86_400.0 {
        format!("{:.1} h ago", d / 3600.0)
    } else {
        format!("{:.1} d ago", d / 86_400.0)
    }
}

/// The table of `rows` as text (columns aligned: run, steps, last checkpoint, state; a header;
/// a count of runs per state), ages relative to `now` (Unix seconds).
pub fn render(rows: &[StatusRow], now: f64) -> String {
    // The state last: a failure's message is as long as it is without widening the others.
    let header = ["run", "steps", "last checkpoint", "state"];
    let cells: Vec<[String; 4]> = rows
        .iter()
        .map(|r| {
            let steps = match (r.steps, r.total) {
                (Some(s), Some(t)) => format!("{s}/{t}"),
                (Some(s), None) => s.to_string(),
                (None, Some(t)) => format!("0/{t}"),
                (None, None) => "0".into(),
            };
            let when = r
                .last_checkpoint
                .map(|t| format!("{} ({})", utc(t), ago(t, now)))
                .unwrap_or_else(|| "-".into());
            [r.run.clone(), steps, when, r.state.describe(r.steps)]
        })
        .collect();
    let mut width = header.map(str::len);
    for c in &cells {
        for (w, s) in width.iter_mut().zip(c) {
            *w = (*w).max(s.chars().count());
        }
    }
    let line = |c: [&str; 4]| {
        let mut s = String::new();
        for (i, (text, w)) in c.iter().zip(width).enumerate() {
            if i + 1 == c.len() {
                s += text;
            } else {
                s += &format!("{text:<w$}  ");
            }
        }
        s.trim_end().to_string() + "\n"
    };
    let mut out = line(header);
    for c in &cells {
        out += &line([&c[0], &c[1], &c[2], &c[3]]);
    }
    let count = |f: fn(&RunState) -> bool| rows.iter().filter(|r| f(&r.state)).count();
    out += &format!(
        "{} run(s): {} complete, {} running, {} interrupted, {} failed, {} not started\n",
        rows.len(),
        count(|s| matches!(s, RunState::Complete)),
        count(|s| matches!(s, RunState::Running { .. })),
        count(|s| matches!(s, RunState::Interrupted { .. })),
        count(|s| matches!(s, RunState::Failed(_))),
        count(|s| matches!(s, RunState::NotStarted)),
    );
    out
}

/// [`render`] of [`status`] now.
pub fn table(plan: &[Planned]) -> String {
    render(&status(plan), unix_now())
}

#[cfg(test)]
mod tests {
    use std::collections::HashMap;

    use super::*;
    use crate::experiment::layout::{
        write_record, RunRecord, Segment, Summary, SweepRecord, Timing,
    };
    use crate::nn::{Head, UNetConfig};
    use crate::train::checkpoint::{write_tensors, CheckpointInfo};

    /// A `last.safetensors` at `step` (no tensors: the status reads the header only).
    fn checkpoint_at(dir: &RunDir, step: u64) {
        let tiny = UNetConfig::preset("tiny", Head::Depth).unwrap();
        let info = CheckpointInfo {
            experiment: Some("r".into()),
            step,
            ..CheckpointInfo::new(tiny, [8, 8], "standard")
        };
        let meta = HashMap::from([(
            "calibconv".to_string(),
            serde_json::to_string(&info).unwrap(),
        )]);
        write_tensors(&dir.last_checkpoint(), &[], meta).unwrap();
    }

    fn segments(dir: &RunDir, segs: Vec<Segment>) {
        let record = RunRecord {
            experiment: "r".into(),
            invocations: Vec::new(),
            segments: segs,
        };
        write_record(&dir.run_json(), &record).unwrap();
    }

    fn ended(reason: SegmentEnd, message: &str) -> Segment {
        let mut s = Segment::begin(0);
        s.end = Some(s.start + 1.0);
        s.reason = Some(reason);
        s.message = Some(message.into());
        s
    }

    fn summary(steps: u64) -> Summary {
        Summary {
            experiment: "r".into(),
            seed: None,
            steps,
            steps_this_run: steps,
            first_loss: 1.0,
            last_loss: 0.5,
            best: None,
            images_per_s: 1.0,
            seconds: 1.0,
            timing: Timing::default(),
            last_checkpoint: "l".into(),
            best_checkpoint: None,
        }
    }

    fn sweep_failure(error: &str) -> SweepRecord {
        SweepRecord {
            experiment: "r".into(),
            file: "r.toml".into(),
            overlay: Default::default(),
            seed: None,
            level: 0,
            depends_on: Vec::new(),
            git: None,
            status: SweepStatus::Failed,
            action: None,
            seconds: None,
            finished_unix: None,
            error: Some(error.into()),
            experiment_text: String::new(),
        }
    }

    #[test]
    fn every_state_is_read_from_the_records() {
        let tmp = tempfile::tempdir().unwrap();
        let dir = |n: &str| {
            let d = RunDir::new(tmp.path().join(n));
            std::fs::create_dir_all(d.checkpoints()).unwrap();
            d
        };
        let row = |d: &RunDir| run_status(d, d.name(), &["test"], Some(10));
        // A run with a checkpoint at `step` whose one segment ended with `reason`.
        let ended_run = |name: &str, step: u64, reason: SegmentEnd, message: &str| {
            let d = dir(name);
            checkpoint_at(&d, step);
            segments(&d, vec![ended(reason, message)]);
            d
        };

        let new = dir("new");
        assert_eq!(row(&new).state, RunState::NotStarted);
        assert_eq!(row(&new).steps, None);

        // Stopped on a signal at step 4 (or killed: no segment end; the same state).
        let stopped = ended_run(
            "stopped",
            4,
            SegmentEnd::Interrupted,
            "stopped by SIGUSR1 at step 4",
        );
        let r = row(&stopped);
        assert_eq!(
            r.state,
            RunState::Interrupted {
                evaluations_left: false
            }
        );
        assert_eq!(r.steps, Some(4));
        assert!(r.last_checkpoint.is_some());
        assert_eq!(r.state.describe(r.steps), "interrupted at step 4");

        // A run that a process holds: running, with its PID.
        let held = stopped.lock().unwrap();
        let r = row(&stopped);
        assert_eq!(
            r.state,
            RunState::Running {
                pid: Some(std::process::id()),
                host: None,
                slurm_job: None
            }
        );
        drop(held);

        // Its latest segment failed: the error's first line.
        let failed = ended_run(
            "failed",
            2,
            SegmentEnd::Failed,
            "cannot write x: No space left on device",
        );
        assert_eq!(
            row(&failed).state,
            RunState::Failed("cannot write x: No space left on device".into())
        );

        // A failure recorded by the sweep (before any training): sweep.json's error.
        let refused = dir("refused");
        write_record(
            &refused.sweep_json(),
            &sweep_failure("holds another run\nmore"),
        )
        .unwrap();
        assert_eq!(
            row(&refused).state,
            RunState::Failed("holds another run".into())
        );

        // Trained, evaluation missing; then complete.
        let done = dir("done");
        checkpoint_at(&done, 10);
        write_record(&done.summary_json(), &summary(10)).unwrap();
        assert_eq!(
            row(&done).state,
            RunState::Interrupted {
                evaluations_left: true
            }
        );
        std::fs::create_dir_all(done.eval_dir("test")).unwrap();
        std::fs::write(done.metrics_json("test"), "{}").unwrap();
        let r = row(&done);
        assert_eq!((r.state.clone(), r.steps), (RunState::Complete, Some(10)));

        // An unreadable record is a failed row naming the file, not an error of the table.
        let broken = dir("broken");
        std::fs::write(broken.run_json(), "{").unwrap();
        match row(&broken).state {
            RunState::Failed(e) => assert!(e.contains("run.json"), "{e}"),
            other => panic!("{other:?}"),
        }
    }

    #[test]
    fn the_table_has_a_row_per_run_and_counts_the_states() {
        let at = 1_764_936_000.0; // 2025-12-05 12:00 UTC
        let rows = vec![
            StatusRow {
                run: "seed-0/a".into(),
                state: RunState::Complete,
                steps: Some(400),
                total: Some(400),
                last_checkpoint: Some(at),
            },
            StatusRow {
                run: "seed-0/long-name".into(),
                state: RunState::Running {
                    pid: Some(7),
                    host: Some("n1".into()),
                    slurm_job: Some("12_3".into()),
                },
                steps: Some(120),
                total: None,
                last_checkpoint: Some(at + 30.0),
            },
            StatusRow {
                run: "seed-0/c".into(),
                state: RunState::NotStarted,
                steps: None,
                total: Some(150),
                last_checkpoint: None,
            },
        ];
        let text = render(&rows, at + 170.0);
        let lines: Vec<&str> = text.lines().collect();
        assert_eq!(lines.len(), 5, "{text}");
        // Columns aligned: each column starts where its header does.
        for (header, cells) in [
            (
                "state",
                [
                    "complete",
                    "running (SLURM 12_3, pid 7) on n1",
                    "not started",
                ],
            ),
            ("steps", ["400/400", "120", "0/150"]),
            (
                "last checkpoint",
                [
                    "2025-12-05 12:00 UTC (3 min ago)",
                    "2025-12-05 12:00 UTC (2 min ago)",
                    "-",
                ],
            ),
        ] {
            let at = lines[0].find(header).unwrap();
            for (line, cell) in lines[1..4].iter().zip(cells) {
                assert_eq!(line.get(at..at + cell.len()), Some(cell), "{text}");
            }
        }
        assert!(lines[1].starts_with("seed-0/a "), "{text}");
        assert_eq!(
            lines[4],
            "3 run(s): 1 complete, 1 running, 0 interrupted, 0 failed, 1 not started"
        );
        assert_eq!(utc(0.0), "1970-01-01 00:00 UTC");
        assert_eq!(utc(951_782_400.0), "2000-02-29 00:00 UTC");
    }
}
