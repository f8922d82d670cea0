//! An in-memory cache of offsets keyed by (camera, input size, geometry, input frame), so a
//! network builds each layer's offsets once however many layers share them.

use std::collections::HashMap;
use std::sync::{Arc, Mutex, OnceLock};

use super::{compute_offsets, InputFrame, LayerGeometry, Offsets};
use crate::camera::Camera;
use crate::error::Result;

type Key = (String, [usize; 2], LayerGeometry, InputFrame);

fn cache() -> &'static Mutex<HashMap<Key, Arc<Offsets>>> {
    static CACHE: OnceLock<Mutex<HashMap<Key, Arc<Offsets>>>> = OnceLock::new();
    CACHE.get_or_init(Default::default)
}

/// [`compute_offsets`], computed once per key for the life of the process.
///
/// The camera part of the key is its `Debug` text, which prints every `f64` exactly, so two
/// cameras share an entry only if all their parameters are bit-identical.
pub fn cached_offsets(
    camera: &Camera,
    input_size: [usize; 2],
    geometry: &LayerGeometry,
    frame: &InputFrame,
) -> Result<Arc<Offsets>> {
    let key = (format!("{camera:?}"), input_size, *geometry, *frame);
    if let Some(hit) = cache().lock().expect("offset cache poisoned").get(&key) {
        return Ok(hit.clone());
    }
    // Computed outside the lock: other layers keep going meanwhile.
    let offsets = Arc::new(compute_offsets(camera, input_size, geometry, frame)?);
    let mut map = cache().lock().expect("offset cache poisoned");
    Ok(map.entry(key).or_insert(offsets).clone())
}
