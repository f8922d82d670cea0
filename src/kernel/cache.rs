//! The offsets cache: each layer's offsets computed once per (camera, input size, geometry,
//! input frame), however many layers or networks share them.
//!
//! Lifetime: entries live for the process (a network's offsets are small next to its plans, and
//! a sweep builds the same cameras' networks again and again); [`clear_offsets_cache`] drops
//! them. The only owner is this module: callers hold `Arc`s to entries, which stay valid after
//! a clear.

use std::sync::{Arc, Mutex, OnceLock};

use super::{compute_offsets, InputFrame, LayerGeometry, Offsets};
use crate::camera::Camera;
use crate::error::Result;

/// What the offsets of a layer depend on. The camera is compared by value (`PartialEq` on its
/// parameters), so two cameras share an entry only if all their parameters are equal.
#[derive(Clone, Debug, PartialEq)]
struct OffsetsKey {
    camera: Camera,
    input_size: [usize; 2],
    geometry: LayerGeometry,
    frame: InputFrame,
}

/// The entries: a few cameras times a few levels, scanned linearly (the camera has no `Hash`:
/// it holds `f64`s).
type Entries = Mutex<Vec<(OffsetsKey, Arc<Offsets>)>>;

fn cache() -> &'static Entries {
    static CACHE: OnceLock<Entries> = OnceLock::new();
    CACHE.get_or_init(Default::default)
}

fn lookup(key: &OffsetsKey) -> Option<Arc<Offsets>> {
    let map = cache().lock().expect("offset cache poisoned");
    map.iter().find(|(k, _)| k == key).map(|(_, v)| v.clone())
}

/// [`compute_offsets`], computed once per key for the life of the process (or until
/// [`clear_offsets_cache`]).
pub fn cached_offsets(
    camera: &Camera,
    input_size: [usize; 2],
    geometry: &LayerGeometry,
    frame: &InputFrame,
) -> Result<Arc<Offsets>> {
    let key = OffsetsKey {
        camera: camera.clone(),
        input_size,
        geometry: *geometry,
        frame: *frame,
    };
    if let Some(hit) = lookup(&key) {
        return Ok(hit);
    }
    // Computed outside the lock: other layers keep going meanwhile.
    let offsets = Arc::new(compute_offsets(camera, input_size, geometry, frame)?);
    let mut map = cache().lock().expect("offset cache poisoned");
    if let Some((_, v)) = map.iter().find(|(k, _)| *k == key) {
        return Ok(v.clone());
    }
    map.push((key, offsets.clone()));
    Ok(offsets)
}

/// Drops every cached entry (`Arc`s held elsewhere stay valid).
pub fn clear_offsets_cache() {
    cache().lock().expect("offset cache poisoned").clear();
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::camera::{Intrinsics, KannalaBrandt};

    /// The cache's half of `calibconv_geometry`'s `kernel::tests::deterministic`.
    #[test]
    fn deterministic_and_cached() {
        let intrinsics = Intrinsics::from_parts([40.0, 40.0, 63.5, 47.5], [128, 96]);
        let cam = Camera::KannalaBrandt(
            KannalaBrandt::new(intrinsics, [0.0, -0.01, 0.0, 0.0], 195.0).unwrap(),
        );
        let g = LayerGeometry::same(5);
        let a = compute_offsets(&cam, [48, 64], &g, &InputFrame::default()).unwrap();
        let b = compute_offsets(&cam, [48, 64], &g, &InputFrame::default()).unwrap();
        assert_eq!(a, b);
        let c1 = cached_offsets(&cam, [48, 64], &g, &InputFrame::default()).unwrap();
        let c2 = cached_offsets(&cam, [48, 64], &g, &InputFrame::default()).unwrap();
        assert!(std::sync::Arc::ptr_eq(&c1, &c2));
        assert_eq!(*c1, a);
    }
}
