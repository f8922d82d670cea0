use super::*;
use crate::data::synth::config::tiny_config;
use crate::data::synth::{synthesize, GenerateOptions};
use tch::Kind;

/// A tiny F195 set (16 px wide) and a pinhole set, written once per test.
fn tiny_sets(out: &Path) {
    let mut raw = tiny_config(out, [4, 16, 3, 24]);
    raw.sets.retain(|s| s.name == "f195" || s.name == "pers");
    let plan = raw.resolve(Path::new("t.toml")).unwrap();
    synthesize(&plan, &GenerateOptions::default()).unwrap();
}

fn config() -> LoaderConfig {
    LoaderConfig {
        batch_size: 4,
        seed: 5,
        ..Default::default()
    }
}

#[test]
fn fractions_are_nested_seeded_subsets_in_manifest_order() {
    let tmp = tempfile::tempdir().unwrap();
    tiny_sets(tmp.path());
    let open = || Dataset::open(&tmp.path().join("f195"), Split::Train, config()).unwrap();
    let all = open();
    let n = all.len();
    assert!(n >= 6, "{n}");
    let ids = |d: &Dataset| d.ids().to_vec();
    let quarter = open().keep_fraction(0.25, 3).unwrap();
    let half = open().keep_fraction(0.5, 3).unwrap();
    assert_eq!(quarter.len(), (n as f64 * 0.25).round() as usize);
    assert_eq!(half.len(), (n as f64 * 0.5).round() as usize);
    // Nested, in manifest order, the same for the same seed, another for another seed.
    assert!(ids(&quarter).iter().all(|id| ids(&half).contains(id)));
    let position = |id: &String| all.ids().iter().position(|a| a == id).unwrap();
    let order: Vec<usize> = ids(&half).iter().map(position).collect();
    assert!(order.windows(2).all(|w| w[0] < w[1]), "{order:?}");
    assert_eq!(ids(&open().keep_fraction(0.5, 3).unwrap()), ids(&half));
    assert_ne!(ids(&open().keep_fraction(0.5, 4).unwrap()), ids(&half));
    assert_eq!(ids(&open().keep_fraction(1.0, 3).unwrap()), ids(&all));
    assert_eq!(open().keep_fraction(1e-9, 3).unwrap().len(), 1);
    for bad in [0.0, -0.5, 1.5, f64::NAN] {
        assert!(open().keep_fraction(bad, 3).is_err(), "{bad}");
    }
    // Batches serve the subset only.
    let served: usize = half.batches(0, 0).map(|b| b.unwrap().ids.len()).sum();
    assert_eq!(served, half.len());
}

#[test]
fn batches_follow_the_contract_with_padding() {
    let tmp = tempfile::tempdir().unwrap();
    tiny_sets(tmp.path());
    let ds = Dataset::open(
        &tmp.path().join("f195"),
        Split::Train,
        LoaderConfig {
            input: InputSize::Multiple(16),
            ..config()
        },
    )
    .unwrap();
    // 24 x 21 stored (1080x960 scaled by 24/1080), padded to 32 x 32.
    assert_eq!(ds.camera().size(), [24, 21]);
    assert_eq!(ds.input_size(), [32, 32]);
    assert_eq!(ds.input_frame().padding, [8, 11]);
    let batches: Vec<Batch> = ds.batches(0, 0).map(|b| b.unwrap()).collect();
    assert_eq!(batches.len(), ds.num_batches());
    let n: usize = batches.iter().map(|b| b.ids.len()).sum();
    assert_eq!(n, ds.len());
    let b = &batches[0];
    assert_eq!(b.image.size(), [4, 3, 32, 32]);
    assert_eq!(b.image.kind(), Kind::Float);
    assert_eq!(b.depth.size(), [4, 1, 32, 32]);
    assert_eq!(b.depth.kind(), Kind::Float);
    assert_eq!(b.labels.size(), [4, 32, 32]);
    assert_eq!(b.labels.kind(), Kind::Int64);
    assert_eq!(b.mask.size(), [4, 1, 32, 32]);
    assert_eq!(b.mask.kind(), Kind::Bool);
    // Units: image in [0, 1], depth in metres (rooms: 0.3 to 25 m) where valid.
    assert!(b.image.max().double_value(&[]) <= 1.0 && b.image.min().double_value(&[]) >= 0.0);
    let valid_depth = b.depth.masked_select(&b.mask);
    assert!(valid_depth.min().double_value(&[]) > 0.1);
    assert!(valid_depth.max().double_value(&[]) < 30.0);
    // Padding: mask false, labels ignored, zeros.
    let pad_mask = b.mask.narrow(3, 24, 8);
    assert_eq!(pad_mask.any().int64_value(&[]), 0);
    let pad_labels = b.labels.narrow(1, 21, 11);
    assert_eq!(pad_labels.ne(IGNORE_LABEL).any().int64_value(&[]), 0);
    assert_eq!(
        b.image
            .narrow(2, 21, 11)
            .abs()
            .sum(Kind::Float)
            .double_value(&[]),
        0.0
    );
    // Labels are class ids or IGNORE; the fisheye corners are ignored and masked.
    let l = &b.labels;
    let valid = l.ge(0).logical_and(&l.lt(NUM_CLASSES as i64));
    assert_eq!(
        valid.logical_or(&l.eq(IGNORE_LABEL)).all().int64_value(&[]),
        1
    );
    assert_eq!(l.int64_value(&[0, 0, 0]), IGNORE_LABEL);
    assert_eq!(b.mask.int64_value(&[0, 0, 0, 0]), 0);
    assert_eq!(b.mask.int64_value(&[0, 0, 10, 12]), 1);
}

#[test]
fn shuffling_is_deterministic_and_skip_skips() {
    let tmp = tempfile::tempdir().unwrap();
    tiny_sets(tmp.path());
    let open = |seed| {
        Dataset::open(
            &tmp.path().join("pers"),
            Split::Train,
            LoaderConfig { seed, ..config() },
        )
        .unwrap()
    };
    let ids = |ds: &Dataset, epoch, skip| -> Vec<String> {
        ds.batches(epoch, skip)
            .flat_map(|b| b.unwrap().ids)
            .collect()
    };
    let (a, b) = (open(5), open(5));
    assert_eq!(ids(&a, 0, 0), ids(&b, 0, 0));
    assert_ne!(ids(&a, 0, 0), ids(&a, 1, 0));
    assert_ne!(ids(&a, 0, 0), ids(&open(6), 0, 0));
    assert_eq!(ids(&a, 3, 1), ids(&a, 3, 0)[4..].to_vec());
    // Same images for the same (seed, epoch), including augmentation.
    let aug = LoaderConfig {
        augment: Augment {
            hflip: true,
            jitter: Some(ColorJitter::default()),
        },
        ..config()
    };
    let c = Dataset::open(&tmp.path().join("pers"), Split::Train, aug).unwrap();
    let x = c.batches(2, 0).next().unwrap().unwrap();
    let y = c.batches(2, 0).next().unwrap().unwrap();
    assert!(x.image.equal(&y.image) && x.labels.equal(&y.labels));
    // Dropping an iterator early does not hang.
    drop(c.batches(0, 0));
}

#[test]
fn flips_are_refused_off_centre_and_flip_every_plane_together() {
    let tmp = tempfile::tempdir().unwrap();
    tiny_sets(tmp.path());
    let root = tmp.path().join("f195");
    let flip = LoaderConfig {
        augment: Augment {
            hflip: true,
            jitter: None,
        },
        shuffle: false,
        ..config()
    };
    // At 24 px the principal point is 0.011 px off centre: allowed.
    let ds = Dataset::open(&root, Split::Train, flip).unwrap();
    let plain = Dataset::open(
        &root,
        Split::Train,
        LoaderConfig {
            shuffle: false,
            ..config()
        },
    )
    .unwrap();
    let (f, p) = (
        ds.batches(0, 0).next().unwrap().unwrap(),
        plain.batches(0, 0).next().unwrap().unwrap(),
    );
    let mut flipped = 0;
    for k in 0..4 {
        let (fi, pi) = (f.labels.get(k), p.labels.get(k));
        if fi.equal(&pi) {
            continue;
        }
        flipped += 1;
        assert!(fi.equal(&pi.flip([1])));
        assert!(f.depth.get(k).equal(&p.depth.get(k).flip([2])));
        assert!(f.mask.get(k).equal(&p.mask.get(k).flip([2])));
    }
    assert!(flipped > 0);
    // Move the principal point off centre: the flip is refused, naming the field.
    let cam = root.join("camera.toml");
    let text = std::fs::read_to_string(&cam).unwrap();
    let cx_line = text
        .lines()
        .find(|l| l.starts_with("cx"))
        .unwrap()
        .to_string();
    std::fs::write(&cam, text.replace(&cx_line, "cx = 12.5")).unwrap();
    let e = Dataset::open(&root, Split::Train, flip)
        .unwrap_err()
        .to_string();
    assert!(e.contains("camera.toml") && e.contains("cx"), "{e}");
}

#[test]
fn broken_sets_give_errors_naming_the_file() {
    let tmp = tempfile::tempdir().unwrap();
    tiny_sets(tmp.path());
    let root = tmp.path().join("pers");
    let ds = Dataset::open(&root, Split::Val, config()).unwrap();
    let id = ds.ids()[0].clone();
    // A label file of the wrong size fails when its batch loads.
    let labels = sample_path(&root, "labels", &id);
    image::GrayImage::new(5, 5).save(&labels).unwrap();
    let e = ds
        .batches(0, 0)
        .find_map(|b| b.err())
        .expect("an error")
        .to_string();
    assert!(e.contains(&format!("{id}.png")) && e.contains("5x5"), "{e}");
    // A missing file fails at open.
    std::fs::remove_file(&labels).unwrap();
    let e = Dataset::open(&root, Split::Val, config())
        .unwrap_err()
        .to_string();
    assert!(
        e.contains(&format!("labels/{id}.png")) && e.contains("missing"),
        "{e}"
    );
    // An input smaller than the images.
    let e = Dataset::open(
        &tmp.path().join("f195"),
        Split::Train,
        LoaderConfig {
            input: InputSize::Exact([8, 8]),
            ..config()
        },
    )
    .unwrap_err()
    .to_string();
    assert!(e.contains("smaller"), "{e}");
}
