//! `calibconv synth` end to end and the data set loader on its output: layout, byte-identical
//! regeneration, resuming, refusing to overwrite, Stanford 2D-3D-S input, batches per the
//! contract of `calibconv::data`.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::process::Output;

use calibconv::camera::{self, CameraModel};
use calibconv::data::format::{Manifest, Split, MANIFEST, SAMPLE_DIRS};
use calibconv::data::loader::{Dataset, InputSize, LoaderConfig};
use calibconv::data::{BatchSource, CLASSES, IGNORE_LABEL};
use tch::Kind;

use crate::common::{self, assert_contains, calibconv, calibconv_in, s, words};

/// What the command printed (stdout, then stderr), after checking that it succeeded or, with
/// `success` false, that it failed.
#[track_caller]
fn printed(o: Output, success: bool) -> String {
    let text = format!("{}{}", common::stdout(&o), common::stderr(&o));
    assert_eq!(o.status.success(), success, "{}: {text}", o.status);
    text
}

/// A tiny run of the default configuration: 3 panoramas 16 px high, 2 views each, 16 px wide;
/// `extra` flags are appended, or replace these defaults.
fn synth(out: &Path, extra: &[&str]) -> Output {
    let mut args: Vec<String> = vec!["synth".into(), "--out".into(), out.display().to_string()];
    let defaults = [
        ("--panoramas", "3"),
        ("--pano-height", "16"),
        ("--views-per-panorama", "2"),
        ("--width", "16"),
    ];
    for (flag, value) in defaults {
        if !extra.contains(&flag) {
            args.extend([flag.to_string(), value.to_string()]);
        }
    }
    args.extend(extra.iter().map(|s| s.to_string()));
    let args: Vec<&str> = args.iter().map(String::as_str).collect();
    calibconv(&args)
}

/// Every file below `root`, relative path -> bytes.
fn tree(root: &Path) -> BTreeMap<PathBuf, Vec<u8>> {
    let mut out = BTreeMap::new();
    let mut stack = vec![root.to_path_buf()];
    while let Some(dir) = stack.pop() {
        for e in std::fs::read_dir(&dir).unwrap() {
            let p = e.unwrap().path();
            if p.is_dir() {
                stack.push(p);
            } else {
                out.insert(
                    p.strip_prefix(root).unwrap().to_path_buf(),
                    std::fs::read(&p).unwrap(),
                );
            }
        }
    }
    out
}

#[test]
fn synth_writes_the_documented_layout_byte_identically() {
    let tmp = tempfile::tempdir().unwrap();
    let (a, b) = (tmp.path().join("a"), tmp.path().join("b"));
    assert_contains(&printed(synth(&a, &[]), true), &["wrote 24 views"]);
    for set in ["f195", "f165", "pers", "rect-f165"] {
        let dir = a.join(set);
        let m = Manifest::read(&dir).unwrap();
        assert!(m.complete);
        assert_eq!(m.counts.samples, 6);
        assert_eq!(m.splits.all().count(), 6);
        assert_eq!(m.classes, CLASSES);
        let cam = camera::load(dir.join("camera.toml")).unwrap();
        assert_eq!(cam.size(), [m.width, m.height]);
        assert_eq!(m.width, 16);
        for id in m.splits.all() {
            for sub in SAMPLE_DIRS {
                assert!(
                    dir.join(sub).join(format!("{id}.png")).is_file(),
                    "{set} {sub} {id}"
                );
            }
        }
    }
    // The rectified set stores the pinhole it was rectified to.
    let rect = std::fs::read_to_string(a.join("rect-f165/camera.toml")).unwrap();
    assert!(rect.contains("model = \"pinhole\""), "{rect}");

    // Same seed, another folder: the same bytes, file for file.
    printed(synth(&b, &[]), true);
    let (ta, tb) = (tree(&a), tree(&b));
    assert_eq!(ta.len(), 4 * (2 + 5 * 6));
    assert_eq!(ta, tb);

    // Again in place: nothing to do, nothing changed.
    assert_contains(&printed(synth(&a, &[]), true), &["nothing to do"]);
    assert_eq!(tree(&a), ta);
}

/// The embedded default needs no file of the repository (its cameras are embedded too): run
/// from an empty folder, it writes the same bytes as from the repository root.
#[test]
fn the_embedded_default_runs_outside_the_repository() {
    let tmp = tempfile::tempdir().unwrap();
    let elsewhere = tmp.path().join("elsewhere");
    std::fs::create_dir(&elsewhere).unwrap();
    let in_root = tmp.path().join("from-root");
    let args =
        words("synth --panoramas 3 --pano-height 16 --views-per-panorama 1 --width 16 --out");
    printed(calibconv(&[&args[..], &[s(&in_root)]].concat()), true);
    printed(
        calibconv_in(&elsewhere, &[&args[..], &["out"]].concat()),
        true,
    );
    let out = elsewhere.join("out");
    for set in ["f195", "f165", "pers", "rect-f165"] {
        let m = Manifest::read(&out.join(set)).unwrap();
        assert!(m.complete, "{set}");
    }
    let m = Manifest::read(&out.join("f195")).unwrap();
    assert_eq!(m.camera_source, "data/cameras/f195.toml");
    assert_eq!(tree(&out), tree(&in_root));
}

#[test]
fn interrupted_runs_resume_and_foreign_folders_are_refused() {
    let tmp = tempfile::tempdir().unwrap();
    let out = tmp.path().join("d");
    printed(synth(&out, &["--set", "f195"]), true);
    let before = tree(&out);
    let dir = out.join("f195");

    // An interrupted run: one sample lost a file, a temporary file is left, and the manifest
    // still says incomplete. The loader refuses it; synth finishes only what is missing.
    let victim = dir.join("depth/p00001_v1.png");
    std::fs::remove_file(&victim).unwrap();
    std::fs::write(dir.join("rgb/.p00001_v1.png.tmp-1234"), b"partial").unwrap();
    let manifest = std::fs::read_to_string(dir.join(MANIFEST)).unwrap();
    std::fs::write(
        dir.join(MANIFEST),
        manifest.replace("\"complete\": true", "\"complete\": false"),
    )
    .unwrap();
    let e = Dataset::open(&dir, Split::Train, LoaderConfig::default()).unwrap_err();
    assert!(e.to_string().contains("complete"), "{e}");
    let msg = printed(synth(&out, &["--set", "f195"]), true);
    assert_contains(&msg, &["wrote 1 views from 1 panoramas"]);
    assert_eq!(tree(&out), before);

    // Another seed or camera width: refused, nothing touched.
    for extra in [&["--seed", "9"][..], &["--width", "20"][..]] {
        let mut args = vec!["--set", "f195"];
        args.extend_from_slice(extra);
        let msg = printed(synth(&out, &args), false);
        let manifest = dir.join(MANIFEST).display().to_string();
        assert_contains(&msg, &["refusing", "--force", &manifest]);
        assert_eq!(tree(&out), before);
    }
    // A manifest from another generator version: refused by synth and by the loader.
    let old = manifest.replace("\"generator_version\": 1", "\"generator_version\": 0");
    std::fs::write(dir.join(MANIFEST), &old).unwrap();
    let msg = printed(synth(&out, &["--set", "f195"]), false);
    assert_contains(&msg, &["generator version 0"]);
    let e = Dataset::open(&dir, Split::Train, LoaderConfig::default())
        .unwrap_err()
        .to_string();
    assert_contains(&e, &["manifest.json", "version 0"]);
    // --force regenerates (same seed: the same bytes again).
    printed(synth(&out, &["--set", "f195", "--force"]), true);
    assert_eq!(tree(&out), before);

    // A non-empty folder that is not a data set.
    let foreign = tmp.path().join("mine");
    std::fs::create_dir_all(foreign.join("f195")).unwrap();
    std::fs::write(foreign.join("f195/notes.txt"), b"keep me").unwrap();
    let msg = printed(synth(&foreign, &["--set", "f195"]), false);
    assert_contains(&msg, &["without a manifest"]);
    assert_eq!(
        std::fs::read(foreign.join("f195/notes.txt")).unwrap(),
        b"keep me"
    );
}

#[test]
fn bad_requests_are_clear_errors() {
    let tmp = tempfile::tempdir().unwrap();
    let out = tmp.path().to_str().unwrap();
    let f195 = "data/cameras/f195.toml";
    // (flags, whether it succeeds, what it prints)
    for (flags, success, parts) in [
        (
            &["--kind", "rectified", "--camera", f195][..],
            false,
            &["195", "180"][..],
        ),
        (&["--kind", "pers", "--camera", f195], false, &["pinhole"]),
        (&["--set", "f999"], false, &["f195"]),
        // --dry-run writes nothing.
        (&["--dry-run"], true, &["rect-f165"]),
    ] {
        let msg = printed(
            calibconv(&[&["synth", "--out", out][..], flags].concat()),
            success,
        );
        assert_contains(&msg, parts);
    }
    assert_eq!(std::fs::read_dir(tmp.path()).unwrap().count(), 0);
}

#[test]
fn a_single_kind_set_loads_as_contract_batches() {
    let tmp = tempfile::tempdir().unwrap();
    let out = tmp.path();
    let o = synth(
        out,
        &[
            "--kind",
            "fisheye",
            "--camera",
            "data/cameras/f165.toml",
            "--name",
            "mine",
            "--panoramas",
            "8",
        ],
    );
    printed(o, true);
    let dir = out.join("mine");
    let config = LoaderConfig {
        batch_size: 2,
        seed: 3,
        input: InputSize::Multiple(8),
        ..Default::default()
    };
    let ds = Dataset::open(&dir, Split::Train, config).unwrap();
    let src: &dyn BatchSource = &ds;
    // 16 x 14 stored, padded to 16 x 16.
    assert_eq!(src.input_size(), [16, 16]);
    assert_eq!(ds.input_frame().padding, [0, 2]);
    let batches: Vec<_> = src.batches(0, 0).map(|b| b.unwrap()).collect();
    assert_eq!(
        batches.iter().map(|b| b.ids.len()).sum::<usize>(),
        src.len()
    );
    let b = &batches[0];
    assert_eq!(b.image.size(), [2, 3, 16, 16]);
    assert_eq!(
        [
            b.image.kind(),
            b.depth.kind(),
            b.labels.kind(),
            b.mask.kind()
        ],
        [Kind::Float, Kind::Float, Kind::Int64, Kind::Bool]
    );
    assert_eq!(b.depth.size(), [2, 1, 16, 16]);
    assert_eq!(b.labels.size(), [2, 16, 16]);
    assert_eq!(b.mask.size(), [2, 1, 16, 16]);
    // Depth in metres where valid, 0 in the padding rows; labels ignored there.
    let d = b.depth.masked_select(&b.mask);
    assert!(d.min().double_value(&[]) > 0.1 && d.max().double_value(&[]) < 30.0);
    let (pad_depth, pad_labels) = (b.depth.narrow(2, 14, 2), b.labels.narrow(1, 14, 2));
    assert_eq!(pad_depth.abs().sum(Kind::Float).double_value(&[]), 0.0);
    assert_eq!(pad_labels.ne(IGNORE_LABEL).any().int64_value(&[]), 0);
    // The same (seed, epoch) gives the same order; another epoch another one.
    let order =
        |epoch| -> Vec<String> { src.batches(epoch, 0).flat_map(|b| b.unwrap().ids).collect() };
    assert_eq!(order(4), order(4));
    // 6 training panoramas x 2 views: 12! orders, so another epoch differs.
    assert_eq!(src.len(), 12);
    assert_ne!(order(5), order(4));
}

#[test]
fn stanford_panoramas_run_through_the_same_synthesis() {
    let tmp = tempfile::tempdir().unwrap();
    let root = tmp.path().join("2D-3D-S");
    calibconv::data::stanford::write_fake_tree(&root, &["area_1", "area_3", "area_5a"], 2, 16)
        .unwrap();
    // F195 views of the tree's panoramas, scaled to 8 px high, in `out`.
    let stanford = |out: &Path, extra: &[&str]| {
        let args = [
            "synth",
            "--stanford",
            s(&root),
            "--pano-height",
            "8",
            "--set",
            "f195",
        ];
        calibconv(&[&args[..], &["--out", s(out)], extra].concat())
    };
    let out = tmp.path().join("out");
    let views = ["--views-per-panorama", "2", "--width", "16"];
    printed(stanford(&out, &views), true);
    let m = Manifest::read(&out.join("f195")).unwrap();
    assert_eq!(m.counts.panoramas, 6);
    // Fold 1: area 5 is the test split, the other areas train and val.
    assert_eq!(m.splits.test.len(), 4);
    assert!(m.splits.test.iter().all(|id| id.starts_with("area_5a_")));
    assert!(m
        .splits
        .train
        .iter()
        .chain(&m.splits.val)
        .all(|id| !id.starts_with("area_5")));
    assert!(m.panorama_source.contains("2D-3D-S"));
    // The labels decode to the 13 classes + unknown and the loader serves them.
    let ds = Dataset::open(&out.join("f195"), Split::Test, LoaderConfig::default()).unwrap();
    let b = ds.batches(0, 0).next().unwrap().unwrap();
    let l = b.labels;
    assert!(l.ge(0).logical_and(&l.lt(13)).any().int64_value(&[]) == 1);

    // An unknown class index in a semantic image stops the run, naming the file.
    let sem = std::fs::read_dir(root.join("area_1/pano/semantic"))
        .unwrap()
        .next()
        .unwrap()
        .unwrap()
        .path();
    let mut img = image::open(&sem).unwrap().to_rgb8();
    img.put_pixel(0, 0, image::Rgb([0, 2, 0]));
    img.save(&sem).unwrap();
    let msg = printed(stanford(&tmp.path().join("out2"), &[]), false);
    assert_contains(&msg, &[&sem.display().to_string(), "index 512"]);
}
