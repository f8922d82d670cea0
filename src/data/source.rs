//! Where `synth`'s panoramas come from: the [`PanoramaSource`] trait, its split assignment
//! and the procedural source (the Stanford 2D-3D-S source in `stanford.rs` is the other).

use crate::data::format::Split;
use crate::data::panorama::{render_procedural, Panorama};
use crate::data::rng::{tag, Rng};
use crate::error::Result;

/// A list of panoramas with their names and splits.
pub trait PanoramaSource: Sync {
    /// Number of panoramas.
    fn len(&self) -> usize;
    /// Whether there are none.
    fn is_empty(&self) -> bool {
        self.len() == 0
    }
    /// Name of panorama `i`, the prefix of its sample ids (file-name safe).
    fn name(&self, i: usize) -> String;
    /// A number identifying panorama `i` independently of which subset was selected (seeds
    /// its view orientations).
    fn key(&self, i: usize) -> u64;
    /// The split panorama `i` belongs to.
    fn split(&self, i: usize) -> Split;
    /// Loads (or renders) panorama `i`.
    fn load(&self, i: usize) -> Result<Panorama>;
    /// A description for the manifest's `panorama_source`.
    fn describe(&self) -> String;
}

/// Assigns `n` items to splits: a seeded shuffle, then `round(n test)` test, `round(n val)`
/// val, the rest train (at least one item for a non-zero fraction when `n >= 3`).
pub fn assign_splits(n: usize, val: f64, test: f64, seed: u64) -> Vec<Split> {
    let count = |f: f64| {
        let k = (n as f64 * f).round() as usize;
        if f > 0.0 && k == 0 && n >= 3 {
            1
        } else {
            k
        }
    };
    let (n_test, n_val) = (count(test).min(n), count(val));
    let n_val = n_val.min(n - n_test);
    let mut order: Vec<usize> = (0..n).collect();
    Rng::derive(seed, &[tag("split")]).shuffle(&mut order);
    let mut out = vec![Split::Train; n];
    for (k, &i) in order.iter().enumerate() {
        out[i] = if k < n_test {
            Split::Test
        } else if k < n_test + n_val {
            Split::Val
        } else {
            Split::Train
        };
    }
    out
}

/// The procedural panoramas of a seed: `p00000`, `p00001`, ...
pub struct ProceduralSource {
    seed: u64,
    height: usize,
    splits: Vec<Split>,
}

impl ProceduralSource {
    /// `count` panoramas of `2 height x height` pixels, split by the fractions `val` and `test`
    /// (the rest train).
    pub fn new(seed: u64, count: usize, height: usize, val: f64, test: f64) -> Self {
        ProceduralSource {
            seed,
            height,
            splits: assign_splits(count, val, test, seed),
        }
    }
}

impl PanoramaSource for ProceduralSource {
    fn len(&self) -> usize {
        self.splits.len()
    }
    fn name(&self, i: usize) -> String {
        format!("p{i:05}")
    }
    fn key(&self, i: usize) -> u64 {
        i as u64
    }
    fn split(&self, i: usize) -> Split {
        self.splits[i]
    }
    fn load(&self, i: usize) -> Result<Panorama> {
        Ok(render_procedural(self.seed, i as u64, self.height).1)
    }
    fn describe(&self) -> String {
        "procedural".into()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn splits_partition_the_panoramas() {
        let s = assign_splits(20, 0.1, 0.1, 3);
        let count = |k| s.iter().filter(|&&x| x == k).count();
        assert_eq!(
            (count(Split::Train), count(Split::Val), count(Split::Test)),
            (16, 2, 2)
        );
        assert_eq!(s, assign_splits(20, 0.1, 0.1, 3));
        assert_ne!(s, assign_splits(20, 0.1, 0.1, 4));
        // Tiny sets still get a val and a test panorama.
        let t = assign_splits(3, 0.1, 0.1, 0);
        assert!(t.contains(&Split::Val) && t.contains(&Split::Test));
    }
}
