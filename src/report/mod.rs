//! Figures people would rather look at than numbers, and the report of a sweep's results.
//!
//! - [`kernels`]: the grid of calibrated kernels over a fisheye image (paper Figure 1a).
//! - [`results`]: `calibconv report RESULTS`: reads the run directories of every seed into
//!   [`study::Observations`], writes the tables with intervals over seeds, the paired-difference
//!   table ([`tables`]), radial plots with bands over seeds, qualitative grids ([`grids`]), the
//!   verdict ([`verdict`]), the gain against the field of view ([`fov`]) and `REPORT.md`.
//!   [`stats`] holds the pure statistics (Student t, bootstrap).

pub mod collect;
pub mod curves;
pub mod draw;
pub mod fov;
pub mod grids;
pub mod kernels;
pub mod pointcloud;
pub mod questions;
pub mod radial;
pub mod results;
pub mod stats;
pub mod study;
pub mod tables;
pub mod verdict;

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use crate::error::Result;
use crate::experiment::layout::write_record;
use crate::plots::{line_band_plot, Curve, PlotSpec};

/// Writes `value` as pretty-printed JSON to `out/name` ([`write_record`]: atomically); returns
/// the file's path.
fn write_json(value: &(impl serde::Serialize + ?Sized), out: &Path, name: &str) -> Result<PathBuf> {
    let path = out.join(name);
    write_record(&path, &value)?;
    Ok(path)
}

/// A table's file and its plots: writes `rows` as JSON to `out/json`, then each plot of
/// `plots` (file name in `out`, titles, curves); nothing at all when `rows` is empty. Returns
/// the files written, the JSON first.
fn write_rows_and_plots<R: serde::Serialize>(
    rows: &[R],
    out: &Path,
    json: &str,
    plots: impl IntoIterator<Item = (String, PlotSpec, Vec<Curve>)>,
) -> Result<Vec<PathBuf>> {
    if rows.is_empty() {
        return Ok(Vec::new());
    }
    let mut files = vec![write_json(rows, out, json)?];
    for (name, spec, curves) in plots {
        let file = out.join(name);
        line_band_plot(&file, &spec, &curves)?;
        files.push(file);
    }
    Ok(files)
}

/// `rows` grouped by `key`, groups in key order, rows in their order.
fn group_by<'r, R, K: Ord>(
    rows: impl IntoIterator<Item = &'r R>,
    key: impl Fn(&'r R) -> K,
) -> BTreeMap<K, Vec<&'r R>> {
    let mut groups: BTreeMap<K, Vec<&R>> = BTreeMap::new();
    for r in rows {
        groups.entry(key(r)).or_default().push(r);
    }
    groups
}
