//! The report's data model: a table row is a [`Cell`] (task, block, data set, kernel), observed
//! once per seed; [`Observations`] holds the per-seed values of every (cell, metric) and the
//! per-seed radial curves. The tables, the difference table and the verdict are computed from
//! these, so they can be tested on synthetic numbers without run directories.

use std::collections::{BTreeMap, BTreeSet};
use std::fmt;

use crate::eval::metrics::Metric;

/// The task of a row (the experiment layer's `task`, with an order for tables).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub enum Task {
    Depth,
    Segmentation,
}

impl Task {
    /// `depth` or `segmentation`.
    pub fn name(self) -> &'static str {
        match self {
            Task::Depth => "depth",
            Task::Segmentation => "segmentation",
        }
    }

    /// `depth` or `seg` (file names).
    pub fn short(self) -> &'static str {
        match self {
            Task::Depth => "depth",
            Task::Segmentation => "seg",
        }
    }
}

impl From<crate::experiment::Task> for Task {
    fn from(t: crate::experiment::Task) -> Self {
        match t {
            crate::experiment::Task::Depth => Task::Depth,
            crate::experiment::Task::Segmentation => Task::Segmentation,
        }
    }
}

impl fmt::Display for Task {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.name())
    }
}

/// The paper's blocks: **BL** (trained on Pers, evaluated as is: no `model.init`) and **FT**
/// (fine-tuned from a BL checkpoint).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub enum Block {
    Bl,
    Ft,
}

impl fmt::Display for Block {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(match self {
            Block::Bl => "BL",
            Block::Ft => "FT",
        })
    }
}

/// Kernel labels of the paper's rows.
pub const STANDARD: &str = "standard";
pub const CALIBRATED: &str = "calibrated";
pub const RECTIFIED: &str = "rectified";
/// CAM-Convs' camera maps on standard kernels, and calibrated offsets that keep learning
/// (the kinds beyond the paper's, `calibconv::nn::ConvKind`).
pub const CAMCONV: &str = "camconv";
pub const CALIBRATED_LEARNED: &str = "calibrated-learned";
/// Kernel labels in table order.
pub const KERNELS: [&str; 5] = [STANDARD, CALIBRATED, RECTIFIED, CAMCONV, CALIBRATED_LEARNED];

/// One row of a table: what was trained and how it was evaluated.
#[derive(Clone, Debug, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub struct Cell {
    pub task: Task,
    pub block: Block,
    /// `PERS`, `F195`, `F165` (or an evaluation's own name).
    pub dataset: String,
    /// [`STANDARD`], [`CALIBRATED`], [`RECTIFIED`] (standard kernels on rectified images).
    pub kernel: String,
}

impl Cell {
    pub fn new(task: Task, block: Block, dataset: &str, kernel: &str) -> Self {
        Cell {
            task,
            block,
            dataset: dataset.to_string(),
            kernel: kernel.to_string(),
        }
    }

    /// The same row with another kernel.
    pub fn with_kernel(&self, kernel: &str) -> Self {
        Cell {
            kernel: kernel.to_string(),
            ..self.clone()
        }
    }

    /// The key tables sort rows by: task, block, PERS / F195 / F165 / others, kernel order.
    pub fn order(&self) -> (Task, Block, usize, String, usize, String) {
        let d = ["PERS", "F195", "F165"]
            .iter()
            .position(|s| *s == self.dataset)
            .unwrap_or(9);
        let k = KERNELS.iter().position(|s| *s == self.kernel).unwrap_or(9);
        (
            self.task,
            self.block,
            d,
            self.dataset.clone(),
            k,
            self.kernel.clone(),
        )
    }
}

impl fmt::Display for Cell {
    /// `FT F195 calibrated`.
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "{} {} {}", self.block, self.dataset, self.kernel)
    }
}

/// Per-seed values of a (cell, metric), by seed.
pub type PerSeed = BTreeMap<u64, f64>;

/// Everything the tables and the verdict need, per seed.
#[derive(Clone, Debug, Default)]
pub struct Observations {
    /// The set's value of each metric of each cell, per seed (under the report's averaging).
    pub values: BTreeMap<(Cell, Metric), PerSeed>,
    /// The value of each metric per radial bin (inner to outer, NaN where a bin is empty),
    /// per seed; every seed's curve has the same bins.
    pub radial: BTreeMap<(Cell, Metric), BTreeMap<u64, Vec<f64>>>,
}

impl Observations {
    /// The per-seed values of `cell`'s `metric` (empty if never observed).
    pub fn get(&self, cell: &Cell, metric: Metric) -> PerSeed {
        self.values
            .get(&(cell.clone(), metric))
            .cloned()
            .unwrap_or_default()
    }

    /// Records one value.
    pub fn insert(&mut self, cell: &Cell, metric: Metric, seed: u64, value: f64) {
        self.values
            .entry((cell.clone(), metric))
            .or_default()
            .insert(seed, value);
    }

    /// Every seed observed anywhere.
    pub fn seeds(&self) -> BTreeSet<u64> {
        self.values
            .values()
            .flat_map(|m| m.keys().copied())
            .collect()
    }

    /// The cells observed, in table order.
    pub fn cells(&self) -> Vec<Cell> {
        let set: BTreeSet<&Cell> = self.values.keys().map(|(c, _)| c).collect();
        let mut cells: Vec<Cell> = set.into_iter().cloned().collect();
        cells.sort_by_key(|c| c.order());
        cells
    }
}

/// Per seed, `a - b` over the seeds both have.
pub fn paired_difference(a: &PerSeed, b: &PerSeed) -> PerSeed {
    a.iter()
        .filter_map(|(s, x)| b.get(s).map(|y| (*s, x - y)))
        .collect()
}
