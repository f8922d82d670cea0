//! Experiment files for the tests. [`ExperimentFile::tiny`] is the one experiment they start
//! from; each test changes what it needs key by key, so its differences from that experiment are
//! spelled out where it is, and the keys every test shares are written once here.

use std::path::{Path, PathBuf};

use toml::{Table, Value};

/// An experiment file being put together, as a TOML table.
#[derive(Clone, Debug)]
pub struct ExperimentFile(Table);

/// What [`ExperimentFile::tiny`] starts from (`NAME` and `CAMERA` are filled in).
const TINY: &str = r#"
name = "NAME"
task = "depth"
device = "cpu"
output = "runs"
model = { preset = "tiny", kernel = "standard" }
input = { camera = "CAMERA", padding = [8, 0], size = [16, 16] }
data = {}
train = { steps = 2, batch_size = 2 }
optimizer = { lr = 1e-3 }
"#;

impl ExperimentFile {
    /// A depth experiment `name` on the CPU: the tiny U-Net with standard kernels, the F195
    /// camera image padded by `[8, 0]` and scaled to 16x16, 2 steps of batches of 2, Adam at
    /// learning rate 1e-3, its run in `runs/NAME` (relative to the current directory), and no data
    /// yet (set `data.train` and the others).
    pub fn tiny(name: &str) -> Self {
        let camera = super::root().join("data/cameras/f195.toml");
        let table: Table = TINY.parse().expect("TINY is TOML");
        ExperimentFile(table)
            .set("name", name)
            .set_path("input.camera", &camera)
    }

    /// Sets `key` (dotted: `train.steps`; missing tables are added) to `value`.
    pub fn set(mut self, key: &str, value: impl Into<Value>) -> Self {
        let (table, last) = self.parent(key);
        table.insert(last.to_string(), value.into());
        self
    }

    /// Pads the F195 camera image (1080x960) by `[0, 120]` to a square and scales it to
    /// `side` x `side`.
    pub fn square(self, side: i64) -> Self {
        self.set("input.padding", vec![0, 120])
            .set("input.size", vec![side, side])
    }

    /// Sets `key` to a path, as a string.
    pub fn set_path(self, key: &str, path: &Path) -> Self {
        self.set(key, path.display().to_string())
    }

    /// Sets `key` to a value written in TOML, such as `{ toy = 4, split = "train" }`.
    ///
    /// # Panics
    /// If `value` is not a TOML value.
    pub fn set_toml(self, key: &str, value: &str) -> Self {
        let mut doc: Table = format!("value = {value}")
            .parse()
            .unwrap_or_else(|e| panic!("{key} = {value}: {e}"));
        self.set(key, doc.remove("value").unwrap())
    }

    /// Removes `key`.
    ///
    /// # Panics
    /// If there is no such key (the test would not test what it says).
    pub fn remove(mut self, key: &str) -> Self {
        let (table, last) = self.parent(key);
        assert!(table.remove(last).is_some(), "no `{key}` to remove");
        self
    }

    /// Appends an `[[eval]]` table, written in TOML as an inline table.
    pub fn eval(mut self, table: &str) -> Self {
        let eval = self.0.entry("eval").or_insert_with(|| Value::Array(vec![]));
        let Value::Array(evals) = eval else {
            panic!("`eval` is not an array");
        };
        let mut doc: Table = format!("value = {table}")
            .parse()
            .unwrap_or_else(|e| panic!("[[eval]] {table}: {e}"));
        evals.push(doc.remove("value").unwrap());
        self
    }

    /// The file's text.
    pub fn text(&self) -> String {
        toml::to_string(&self.0).expect("an experiment table serialises")
    }

    /// Writes the file to `path` and returns `path`.
    pub fn write(&self, path: &Path) -> PathBuf {
        std::fs::write(path, self.text())
            .unwrap_or_else(|e| panic!("writing {}: {e}", path.display()));
        path.to_path_buf()
    }

    /// Writes the file to `dir/NAME.toml` and loads it with `calibconv::experiment::load`.
    pub fn load_in(&self, dir: &Path) -> calibconv::experiment::Experiment {
        let name = self.0["name"].as_str().expect("a name");
        let path = self.write(&dir.join(format!("{name}.toml")));
        calibconv::experiment::load(&path)
            .unwrap_or_else(|e| panic!("loading {}: {e:#}", path.display()))
    }

    /// The table holding dotted `key`'s last part, made where missing, and that part.
    fn parent<'k>(&mut self, key: &'k str) -> (&mut Table, &'k str) {
        let mut parts: Vec<&str> = key.split('.').collect();
        let last = parts.pop().unwrap();
        let mut table = &mut self.0;
        for part in parts {
            let next = table
                .entry(part)
                .or_insert_with(|| Value::Table(Table::new()));
            table = next
                .as_table_mut()
                .unwrap_or_else(|| panic!("`{part}` of `{key}` is not a table"));
        }
        (table, last)
    }
}

/// The run options of a test: no resuming, no progress bars, no log lines, the default opener.
pub fn quiet() -> calibconv::experiment::RunOptions<'static> {
    calibconv::experiment::RunOptions {
        resume: false,
        progress: false,
        verbose: false,
        opener: &calibconv::experiment::DefaultOpener,
        stop: calibconv::train::stop::StopFlag::detached(),
    }
}
