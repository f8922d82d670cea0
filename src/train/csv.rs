//! Training logs as CSV, one file per split (`train.csv`, `val.csv`): a `step` column, then one
//! column per scalar in the order of the first row. Rows are appended and flushed as they come.
//!
//! When a run resumes at step `s`, rows after `s` (written after the checkpoint it resumes
//! from) are dropped first, so the file never holds a step twice.

use std::collections::HashMap;
use std::fs::{File, OpenOptions};
use std::io::Write;
use std::path::{Path, PathBuf};

use image::RgbImage;

use crate::error::{Error, Result};
use crate::io::write_bytes_atomic;
use crate::train::Reporter;
use crate::util::fmt_f64;

/// CSV files in a folder, one per split.
#[derive(Debug)]
pub struct CsvLog {
    dir: PathBuf,
    files: HashMap<String, (Vec<String>, File)>,
}

impl CsvLog {
    /// Logs in `dir` (created if needed). With `resume_at = Some(s)`, existing files keep their
    /// header and the rows with `step <= s`; otherwise existing files are replaced.
    pub fn create(dir: &Path, resume_at: Option<u64>) -> Result<Self> {
        std::fs::create_dir_all(dir).map_err(|e| Error::io(dir, e))?;
        let entries = std::fs::read_dir(dir).map_err(|e| Error::io(dir, e))?;
        for entry in entries {
            let path = entry.map_err(|e| Error::io(dir, e))?.path();
            if path.extension().is_some_and(|e| e == "csv") {
                match resume_at {
                    Some(s) => truncate_after(&path, s)?,
                    None => std::fs::remove_file(&path).map_err(|e| Error::io(&path, e))?,
                }
            }
        }
        Ok(CsvLog {
            dir: dir.to_path_buf(),
            files: HashMap::new(),
        })
    }

    /// The file of `split`.
    pub fn path(&self, split: &str) -> PathBuf {
        self.dir.join(format!("{split}.csv"))
    }
}

/// A log read back: its column names (after `step`) and rows `(step, values)`.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct LogTable {
    pub columns: Vec<String>,
    pub rows: Vec<(u64, Vec<f64>)>,
}

impl LogTable {
    /// The values of column `name` as `(step, value)`, if the log has it.
    pub fn column(&self, name: &str) -> Option<Vec<(u64, f64)>> {
        let i = self.columns.iter().position(|c| c == name)?;
        Some(self.rows.iter().map(|(s, v)| (*s, v[i])).collect())
    }
}

/// Reads a log written by [`CsvLog`]; `Ok(None)` if the file does not exist. A malformed row is
/// an error naming the file and the line.
pub fn read_log(path: &Path) -> Result<Option<LogTable>> {
    let text = match std::fs::read_to_string(path) {
        Ok(t) => t,
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(None),
        Err(e) => return Err(Error::io(path, e)),
    };
    let mut lines = text.lines();
    let bad =
        |n: usize, why: &str| Error::InvalidArgument(format!("{} line {n}: {why}", path.display()));
    let header: Vec<String> = match lines.next() {
        Some(h) => h.split(',').map(String::from).collect(),
        None => return Ok(Some(LogTable::default())),
    };
    if header.first().map(String::as_str) != Some("step") {
        return Err(bad(1, "the first column must be `step`"));
    }
    let mut table = LogTable {
        columns: header[1..].to_vec(),
        rows: Vec::new(),
    };
    for (i, line) in lines.enumerate().filter(|(_, l)| !l.trim().is_empty()) {
        let mut cells = line.split(',');
        let step = cells
            .next()
            .and_then(|c| c.trim().parse::<u64>().ok())
            .ok_or_else(|| bad(i + 2, "no step"))?;
        let values = cells
            .map(|c| c.trim().parse::<f64>())
            .collect::<std::result::Result<Vec<f64>, _>>()
            .map_err(|e| bad(i + 2, &e.to_string()))?;
        if values.len() != table.columns.len() {
            return Err(bad(
                i + 2,
                &format!(
                    "{} values for {} columns",
                    values.len(),
                    table.columns.len()
                ),
            ));
        }
        table.rows.push((step, values));
    }
    Ok(Some(table))
}

fn truncate_after(path: &Path, step: u64) -> Result<()> {
    let text = std::fs::read_to_string(path).map_err(|e| Error::io(path, e))?;
    let columns = text.lines().next().map_or(0, |h| h.split(',').count());
    let mut out = String::new();
    for (i, line) in text.lines().enumerate() {
        // A row cut short (a write that failed on a full disk) is dropped with the later ones.
        let keep = i == 0
            || (line.split(',').count() == columns
                && line
                    .split(',')
                    .next()
                    .and_then(|s| s.parse::<u64>().ok())
                    .is_some_and(|s| s <= step));
        if keep {
            out.push_str(line);
            out.push('\n');
        }
    }
    write_bytes_atomic(path, out.as_bytes())
}

impl Reporter for CsvLog {
    fn scalars(&mut self, split: &str, step: u64, values: &[(String, f64)]) -> Result<()> {
        let path = self.path(split);
        let names: Vec<String> = values.iter().map(|(n, _)| n.clone()).collect();
        if !self.files.contains_key(split) {
            let existing = std::fs::read_to_string(&path).ok();
            let mut file = OpenOptions::new()
                .create(true)
                .append(true)
                .open(&path)
                .map_err(|e| Error::io(&path, e))?;
            let header = format!("step,{}", names.join(","));
            match existing.as_deref().and_then(|t| t.lines().next()) {
                Some(h) if h != header => {
                    return Err(Error::InvalidArgument(format!(
                        "{}: existing columns `{h}` differ from `{header}`",
                        path.display()
                    )))
                }
                Some(_) => {}
                None => writeln!(file, "{header}").map_err(|e| Error::io(&path, e))?,
            }
            self.files.insert(split.to_string(), (names.clone(), file));
        }
        let (cols, file) = self.files.get_mut(split).expect("inserted above");
        if *cols != names {
            return Err(Error::InvalidArgument(format!(
                "{}: columns changed from {cols:?} to {names:?}",
                path.display()
            )));
        }
        let row: Vec<String> = values.iter().map(|(_, v)| fmt_f64(*v)).collect();
        writeln!(file, "{step},{}", row.join(",")).map_err(|e| Error::io(&path, e))?;
        file.flush().map_err(|e| Error::io(&path, e))
    }

    fn image(&mut self, _: &str, _: u64, _: &RgbImage) -> Result<()> {
        Ok(())
    }

    fn flush(&mut self) -> Result<()> {
        for (split, (_, f)) in &mut self.files {
            f.sync_data()
                .map_err(|e| Error::io(self.dir.join(format!("{split}.csv")), e))?;
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_log_reads_back_and_a_bad_row_names_its_line() {
        let dir = tempfile::tempdir().unwrap();
        let mut log = CsvLog::create(dir.path(), None).unwrap();
        for step in [10, 20] {
            let values = [
                ("rmse".to_string(), step as f64 / 10.0),
                ("mae".into(), 0.5),
            ];
            log.scalars("val", step, &values).unwrap();
        }
        let t = read_log(&log.path("val")).unwrap().unwrap();
        assert_eq!(t.columns, ["rmse", "mae"]);
        assert_eq!(t.column("rmse").unwrap(), [(10, 1.0), (20, 2.0)]);
        assert!(read_log(&dir.path().join("none.csv")).unwrap().is_none());
        let bad = dir.path().join("bad.csv");
        std::fs::write(&bad, "step,rmse\n10,1.0\n20,x\n").unwrap();
        let e = read_log(&bad).unwrap_err().to_string();
        assert!(e.contains("bad.csv line 3"), "{e}");
    }

    #[test]
    fn rows_append_and_resume_drops_later_steps() {
        let dir = tempfile::tempdir().unwrap();
        let mut log = CsvLog::create(dir.path(), None).unwrap();
        for step in [10, 20, 30] {
            log.scalars(
                "train",
                step,
                &[("loss".into(), step as f64 / 10.0), ("lr".into(), f64::NAN)],
            )
            .unwrap();
        }
        drop(log);
        let text = std::fs::read_to_string(dir.path().join("train.csv")).unwrap();
        assert_eq!(text, "step,loss,lr\n10,1,\n20,2,\n30,3,\n");
        let mut log = CsvLog::create(dir.path(), Some(20)).unwrap();
        log.scalars("train", 30, &[("loss".into(), 3.5), ("lr".into(), 0.1)])
            .unwrap();
        let text = std::fs::read_to_string(dir.path().join("train.csv")).unwrap();
        assert_eq!(text, "step,loss,lr\n10,1,\n20,2,\n30,3.5,0.1\n");
        let err = log
            .scalars("train", 40, &[("loss".into(), 1.0)])
            .unwrap_err();
        assert!(err.to_string().contains("columns changed"), "{err}");
    }

    #[test]
    fn a_row_cut_short_by_a_full_disk_is_dropped_on_resume() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("train.csv");
        // The row of step 15 was cut after its first digit.
        std::fs::write(&path, "step,loss,lr\n10,1,0.1\n1").unwrap();
        drop(CsvLog::create(dir.path(), Some(10)).unwrap());
        assert_eq!(
            std::fs::read_to_string(&path).unwrap(),
            "step,loss,lr\n10,1,0.1\n"
        );
    }
}
