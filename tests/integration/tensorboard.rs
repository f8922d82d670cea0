//! The TensorBoard event files calibconv writes are read by TensorBoard itself: the
//! `tensorboard` Python package's `EventAccumulator` (in `.venv`, installed by `make setup`)
//! finds every scalar with its step and value, and images with their true size.

use std::process::Command;

use image::RgbImage;

use calibconv::train::tensorboard::TensorBoard;
use calibconv::train::Reporter;

/// Scalars are stored as float32.
const TOL: f64 = 1e-6;

const READER: &str = r#"
import json, sys
from tensorboard.backend.event_processing.event_accumulator import EventAccumulator
acc = EventAccumulator(sys.argv[1], size_guidance={"scalars": 0, "images": 0})
acc.Reload()
tags = acc.Tags()
out = {
    "scalars": {t: [[e.step, e.value] for e in acc.Scalars(t)] for t in tags["scalars"]},
    "images": {t: [[e.step, e.width, e.height, len(e.encoded_image_string)] for e in acc.Images(t)]
               for t in tags["images"]},
}
print(json.dumps(out))
"#;

#[test]
fn tensorboard_reads_scalars_and_images() {
    let python = concat!(env!("CARGO_MANIFEST_DIR"), "/.venv/bin/python");
    assert!(
        std::path::Path::new(python).exists(),
        "{python} missing: run `make setup` (it installs the tensorboard package)"
    );
    let dir = tempfile::tempdir().unwrap();
    {
        let mut tb = TensorBoard::create(dir.path()).unwrap();
        for step in 1..=3u64 {
            tb.scalars(
                "train",
                step * 10,
                &[("loss".into(), 1.0 / step as f64), ("lr".into(), 0.5)],
            )
            .unwrap();
        }
        tb.scalars("val", 30, &[("rmse".into(), 0.25)]).unwrap();
        // Not square, so a width / height swap would show.
        let mut img = RgbImage::new(30, 20);
        img.put_pixel(29, 19, image::Rgb([255, 0, 0]));
        tb.image("val/prediction/0", 30, &img).unwrap();
        tb.flush().unwrap();
    } // dropping the writer closes the file
    let out = Command::new(python)
        .arg("-c")
        .arg(READER)
        .arg(dir.path())
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "EventAccumulator failed: {}",
        String::from_utf8_lossy(&out.stderr)
    );
    let doc: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    let loss = doc["scalars"]["train/loss"].as_array().unwrap();
    assert_eq!(loss.len(), 3);
    for (i, e) in loss.iter().enumerate() {
        assert_eq!(e[0].as_u64().unwrap(), 10 * (i as u64 + 1));
        assert!((e[1].as_f64().unwrap() - 1.0 / (i as f64 + 1.0)).abs() < TOL);
    }
    assert_eq!(doc["scalars"]["train/lr"].as_array().unwrap().len(), 3);
    let rmse = &doc["scalars"]["val/rmse"][0];
    assert_eq!(rmse[0].as_u64(), Some(30));
    assert!((rmse[1].as_f64().unwrap() - 0.25).abs() < TOL);
    let img = &doc["images"]["val/prediction/0"][0];
    assert_eq!(img[0].as_u64(), Some(30));
    assert_eq!((img[1].as_u64(), img[2].as_u64()), (Some(30), Some(20)));
    assert!(img[3].as_u64().unwrap() > 0);
}
