//! Adam / AdamW with a state that can be saved and restored (libtorch's optimiser state is not
//! reachable from tch, and an exact `--resume` needs the moments).
//!
//! PyTorch's update (`torch.optim.Adam`, `amsgrad = False`), for step `t` (from 1), gradient
//! `g`, parameter `p`:
//!
//! ```text
//! g = g + wd p                     (Adam: L2 penalty in the gradient)
//! p = p (1 - lr wd)                (AdamW: decoupled weight decay, instead of the line above)
//! m = b1 m + (1 - b1) g
//! v = b2 v + (1 - b2) g^2
//! p = p - lr / (1 - b1^t) * m / (sqrt(v) / sqrt(1 - b2^t) + eps)
//! ```
//!
//! A test checks it against libtorch's own `torch::optim::Adam` / `AdamW` (through tch).

use std::collections::HashMap;
use std::path::Path;

use serde::{Deserialize, Serialize};
use tch::nn::VarStore;
use tch::Tensor;

use super::pytorch::dropped_on_import;
use super::tensors::{stage_tensors, TensorFile};
use crate::error::{Error, Result};
use crate::io::Staged;

/// Optimiser settings.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct AdamConfig {
    /// `[beta1, beta2]`.
    pub betas: [f64; 2],
    pub eps: f64,
    pub weight_decay: f64,
    /// `true`: AdamW (decoupled weight decay); `false`: Adam (L2 in the gradient).
    pub decoupled: bool,
}

impl Default for AdamConfig {
    /// PyTorch's defaults: betas (0.9, 0.999), eps 1e-8, no weight decay, Adam.
    fn default() -> Self {
        AdamConfig {
            betas: [0.9, 0.999],
            eps: 1e-8,
            weight_decay: 0.0,
            decoupled: false,
        }
    }
}

/// Adam over the trainable variables of a [`VarStore`], in name order.
pub struct Adam {
    cfg: AdamConfig,
    params: Vec<(String, Tensor)>,
    m: Vec<Tensor>,
    v: Vec<Tensor>,
    t: u64,
}

impl std::fmt::Debug for Adam {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Adam")
            .field("cfg", &self.cfg)
            .field("params", &self.params.len())
            .field("t", &self.t)
            .finish()
    }
}

impl Adam {
    /// An optimiser for every variable of `vs` that requires a gradient (BatchNorm running
    /// statistics do not).
    pub fn new(vs: &VarStore, cfg: AdamConfig) -> Self {
        let mut params: Vec<(String, Tensor)> = vs
            .variables()
            .into_iter()
            .filter(|(_, t)| t.requires_grad())
            .collect();
        params.sort_by(|a, b| a.0.cmp(&b.0));
        let zeros = |p: &Tensor| p.zeros_like().detach();
        let m = params.iter().map(|(_, p)| zeros(p)).collect();
        let v = params.iter().map(|(_, p)| zeros(p)).collect();
        Adam {
            cfg,
            params,
            m,
            v,
            t: 0,
        }
    }

    /// Steps taken.
    pub fn steps(&self) -> u64 {
        self.t
    }

    /// Clears every parameter's gradient.
    pub fn zero_grad(&mut self) {
        for (_, p) in &mut self.params {
            p.zero_grad();
        }
    }

    /// The global L2 norm of the gradients (0 if none).
    pub fn grad_norm(&self) -> f64 {
        tch::no_grad(|| {
            let mut sq = 0.0;
            for (_, p) in &self.params {
                let g = p.grad();
                if g.defined() {
                    sq += g.square().sum(tch::Kind::Double).double_value(&[]);
                }
            }
            sq.sqrt()
        })
    }

    /// One update with learning rate `lr`. Parameters without a gradient are left alone (their
    /// moments too), as PyTorch does.
    pub fn step(&mut self, lr: f64) {
        self.t += 1;
        let [b1, b2] = self.cfg.betas;
        let t = self.t as i32;
        let (bc1, bc2) = (1.0 - b1.powi(t), 1.0 - b2.powi(t));
        let wd = self.cfg.weight_decay;
        tch::no_grad(|| {
            for (i, (_, p)) in self.params.iter_mut().enumerate() {
                let g = p.grad();
                if !g.defined() {
                    continue;
                }
                let g = if wd != 0.0 && !self.cfg.decoupled {
                    &g + &*p * wd
                } else {
                    g
                };
                if wd != 0.0 && self.cfg.decoupled {
                    let _ = p.g_mul_scalar_(1.0 - lr * wd);
                }
                let m = &mut self.m[i];
                let _ = m.g_mul_scalar_(b1);
                let _ = m.g_add_(&(&g * (1.0 - b1)));
                let v = &mut self.v[i];
                let _ = v.g_mul_scalar_(b2);
                let _ = v.g_add_(&(g.square() * (1.0 - b2)));
                let denom = v.sqrt() / bc2.sqrt() + self.cfg.eps;
                let _ = p.g_sub_(&(&*m / denom * (lr / bc1)));
            }
        });
    }

    /// Saves the moments and step count to `path` (safetensors: `m.NAME`, `v.NAME`; metadata
    /// `adam_step`), atomically.
    pub fn save(&self, path: &Path, extra: HashMap<String, String>) -> Result<()> {
        self.stage(path, extra)?.commit()
    }

    /// [`Adam::save`] up to the rename (see [`crate::io::stage_bytes`]): the trainer writes the
    /// optimiser state and the weights in full before it replaces either.
    pub fn stage(&self, path: &Path, extra: HashMap<String, String>) -> Result<Staged> {
        let mut tensors = Vec::with_capacity(2 * self.params.len());
        for (i, (name, _)) in self.params.iter().enumerate() {
            tensors.push((format!("m.{name}"), self.m[i].shallow_clone()));
            tensors.push((format!("v.{name}"), self.v[i].shallow_clone()));
        }
        let mut meta = extra;
        meta.insert("adam_step".to_string(), self.t.to_string());
        meta.insert(
            "adam_config".to_string(),
            serde_json::to_string(&self.cfg).expect("config serialises"),
        );
        stage_tensors(path, &tensors, meta)
    }

    /// Restores the state written by [`Adam::save`] (same parameter names and shapes, else an
    /// error listing the mismatches). Returns the file's metadata.
    pub fn load(&mut self, path: &Path) -> Result<HashMap<String, String>> {
        let file = TensorFile::open(path)?;
        let meta = file.metadata()?;
        let t = meta
            .get("adam_step")
            .and_then(|s| s.parse::<u64>().ok())
            .ok_or_else(|| Error::Checkpoint {
                path: path.to_path_buf(),
                message: "no `adam_step` metadata: not an optimiser state".into(),
            })?;
        let mut targets = Vec::with_capacity(2 * self.params.len());
        for (i, (name, _)) in self.params.iter().enumerate() {
            targets.push((format!("m.{name}"), self.m[i].shallow_clone()));
            targets.push((format!("v.{name}"), self.v[i].shallow_clone()));
        }
        file.copy_into(&targets, dropped_on_import, |_| false)?;
        self.t = t;
        Ok(meta)
    }
}

#[cfg(test)]
mod tests {
    use tch::nn::{self, OptimizerConfig};
    use tch::{Device, Kind};

    use super::*;

    /// float32 updates of two implementations of the same formula; they differ by rounding
    /// order only.
    const TOL: f64 = 1e-6;

    fn problem(seed: i64) -> (VarStore, Tensor) {
        tch::manual_seed(seed);
        let vs = VarStore::new(Device::Cpu);
        let w = vs.root().randn("w", &[4, 3], 0.0, 1.0);
        (vs, w)
    }

    fn loss(w: &Tensor, step: i64) -> Tensor {
        // A changing quadratic so that the moments matter.
        let target =
            Tensor::arange(12, (Kind::Float, Device::Cpu)).view([4, 3]) * (0.1 * step as f64);
        (w - target).square().sum(Kind::Float) + w.abs().sum(Kind::Float)
    }

    #[test]
    fn matches_libtorch_adam_and_adamw() {
        for (decoupled, wd) in [(false, 0.0), (false, 0.05), (true, 0.05)] {
            let cfg = AdamConfig {
                weight_decay: wd,
                decoupled,
                ..Default::default()
            };
            let (vs_a, w_a) = problem(3);
            let (vs_b, w_b) = problem(3);
            let mut ours = Adam::new(&vs_a, cfg);
            let mut theirs = if decoupled {
                nn::AdamW {
                    wd,
                    ..Default::default()
                }
                .build(&vs_b, 0.01)
                .unwrap()
            } else {
                nn::Adam {
                    wd,
                    ..Default::default()
                }
                .build(&vs_b, 0.01)
                .unwrap()
            };
            for step in 0..20 {
                ours.zero_grad();
                loss(&w_a, step).backward();
                ours.step(0.01);
                theirs.zero_grad();
                loss(&w_b, step).backward();
                theirs.step();
            }
            let diff = (&w_a - &w_b).abs().max().double_value(&[]);
            assert!(diff < TOL, "decoupled {decoupled} wd {wd}: {diff}");
            assert!((&w_a - &problem(3).1).abs().max().double_value(&[]) > 0.05);
        }
    }

    #[test]
    fn first_step_moves_each_weight_by_lr_against_its_gradient_sign() {
        // With m = (1-b1) g, v = (1-b2) g^2 and bias correction, the first update is
        // lr * g / (|g| + eps) = lr * sign(g) for |g| >> eps.
        let (vs, w) = problem(5);
        let w0 = w.detach().copy();
        let mut adam = Adam::new(&vs, AdamConfig::default());
        let g = Tensor::randn([4, 3], (Kind::Float, Device::Cpu));
        (&w * &g).sum(Kind::Float).backward();
        adam.step(0.1);
        let expected = &w0 - g.sign() * 0.1;
        assert!((&w - expected).abs().max().double_value(&[]) < 1e-6);
    }

    #[test]
    fn state_round_trips_so_resumed_updates_are_identical() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("optim.safetensors");
        let (vs_a, w_a) = problem(4);
        let mut a = Adam::new(&vs_a, AdamConfig::default());
        for step in 0..3 {
            a.zero_grad();
            loss(&w_a, step).backward();
            a.step(0.01);
        }
        a.save(&path, HashMap::new()).unwrap();
        let (vs_b, w_b) = problem(9);
        tch::no_grad(|| w_b.shallow_clone().copy_(&w_a));
        let mut b = Adam::new(&vs_b, AdamConfig::default());
        b.load(&path).unwrap();
        assert_eq!(b.steps(), 3);
        for step in 3..6 {
            for (opt, w) in [(&mut a, &w_a), (&mut b, &w_b)] {
                opt.zero_grad();
                loss(w, step).backward();
                opt.step(0.01);
            }
        }
        assert!(w_a.equal(&w_b));
    }
}
