//! The sampling-plan cache, the one owner of every cached [`SamplingPlan`]: plans of layers
//! (keyed by their offsets) and plans of the functional op (keyed by the offsets tensor's
//! identity and version).
//!
//! Lifetime:
//! - Layer plans ([`layer_plan`]) live for the process, like the offsets they come from
//!   ([`crate::kernel::cached_offsets`]): every network built for the same camera and sizes
//!   shares them (same tensor storage).
//! - Functional plans ([`tensor_plan`], used by [`super::deform_conv2d`]) are kept for the last
//!   [`TENSOR_PLANS`] distinct offsets tensors (least recently used evicted). An entry holds a
//!   reference to its offsets tensor, so the storage it is keyed by cannot be freed and reused
//!   while it is cached; its version counter (bumped by every in-place write, through any view)
//!   is part of the key, so a modified tensor gets a new plan. Writes that bypass libtorch (raw
//!   pointers) are not seen: call [`clear_plan_caches`] after them.
//!
//! [`clear_plan_caches`] drops both (plans held by layers stay valid).

use std::sync::{Arc, Mutex, OnceLock};

use tch::{Device, Kind, Tensor};

use super::plan::{Border, ConvGeometry, SamplingPlan};
use crate::error::Result;
use crate::kernel::Offsets;

/// Functional plans kept (each holds its offsets tensor and plan: 216 bytes an output pixel for
/// a 3x3 kernel).
pub const TENSOR_PLANS: usize = 16;

/// A layer's plan: its offsets (by identity: entries of the offsets cache live for the process)
/// and everything else the plan depends on.
struct LayerKey {
    offsets: Arc<Offsets>,
    geom: ConvGeometry,
    kind: Kind,
    border: Border,
    device: Device,
}

impl LayerKey {
    fn matches(&self, o: &LayerKey) -> bool {
        Arc::ptr_eq(&self.offsets, &o.offsets)
            && (self.geom, self.kind, self.border, self.device)
                == (o.geom, o.kind, o.border, o.device)
    }
}

/// A functional call's plan: the offsets tensor by storage address, version, shape and
/// strides, and the convolution's geometry.
#[derive(Clone, Debug, PartialEq, Eq)]
struct TensorKey {
    data: usize,
    version: i64,
    sizes: Vec<i64>,
    strides: Vec<i64>,
    offsets_kind: Kind,
    device: Device,
    input_size: [i64; 2],
    geom: ConvGeometry,
    kind: Kind,
}

#[derive(Default)]
struct Caches {
    layers: Vec<(LayerKey, SamplingPlan)>,
    /// Most recently used last; each entry keeps its offsets tensor alive.
    tensors: Vec<(TensorKey, Tensor, SamplingPlan)>,
}

fn caches() -> &'static Mutex<Caches> {
    static CACHES: OnceLock<Mutex<Caches>> = OnceLock::new();
    CACHES.get_or_init(Default::default)
}

fn lock() -> std::sync::MutexGuard<'static, Caches> {
    caches().lock().expect("plan cache poisoned")
}

/// The plan of a layer with `offsets` on `device` (built once, then shared: same storage).
pub fn layer_plan(
    offsets: &Arc<Offsets>,
    geom: ConvGeometry,
    kind: Kind,
    border: Border,
    device: Device,
) -> Result<SamplingPlan> {
    let key = LayerKey {
        offsets: offsets.clone(),
        geom,
        kind,
        border,
        device,
    };
    let hit = |c: &Caches| {
        c.layers
            .iter()
            .find(|(k, _)| k.matches(&key))
            .map(|(_, p)| p.shallow_clone())
    };
    if let Some(plan) = hit(&lock()) {
        return Ok(plan);
    }
    // Built outside the lock (other layers keep going); the first insert wins.
    let plan = SamplingPlan::from_offsets(offsets, geom, kind, border)?.to_device(device);
    let mut c = lock();
    if let Some(plan) = hit(&c) {
        return Ok(plan);
    }
    c.layers.push((key, plan.shallow_clone()));
    Ok(plan)
}

/// The plan of a functional call ([`SamplingPlan::new`]'s arguments, on the input's device),
/// from the cache when the same offsets tensor (same storage, shape, strides and version) was
/// planned before with the same geometry.
pub fn tensor_plan(
    offsets: &Tensor,
    input_size: [i64; 2],
    geom: ConvGeometry,
    kind: Kind,
    device: Device,
) -> Result<SamplingPlan> {
    let build = || {
        Ok::<_, crate::error::Error>(
            SamplingPlan::new(offsets, input_size, geom, kind)?.to_device(device),
        )
    };
    // Inference tensors have no version counter: never cached.
    let Ok(version) = offsets.f_internal_version() else {
        return build();
    };
    let key = TensorKey {
        data: offsets.data_ptr() as usize,
        version,
        sizes: offsets.size(),
        strides: offsets.stride(),
        offsets_kind: offsets.kind(),
        device,
        input_size,
        geom,
        kind,
    };
    {
        let mut c = lock();
        if let Some(i) = c.tensors.iter().position(|(k, _, _)| *k == key) {
            let entry = c.tensors.remove(i);
            let plan = entry.2.shallow_clone();
            c.tensors.push(entry);
            return Ok(plan);
        }
    }
    let plan = build()?;
    let mut c = lock();
    // A stale entry of the same tensor (older version) goes first.
    c.tensors
        .retain(|(k, _, _)| !(k.data == key.data && k.version != key.version));
    if c.tensors.len() >= TENSOR_PLANS {
        drop(c.tensors.remove(0));
    }
    c.tensors
        .push((key, offsets.shallow_clone(), plan.shallow_clone()));
    Ok(plan)
}

/// Drops every cached plan (plans already handed out stay valid).
pub fn clear_plan_caches() {
    let mut c = lock();
    c.layers.clear();
    c.tensors.clear();
}
