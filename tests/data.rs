//! `calibconv synth` end to end and the data set loader on its output: layout, byte-identical
//! regeneration, resuming, refusing to overwrite, Stanford 2D-3D-S input, batches per the
//! contract of `calibconv::data`.

mod common;

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::process::Output;

use calibconv::camera::{self, CameraModel};
use calibconv::data::format::{Manifest, Split, MANIFEST, SAMPLE_DIRS};
use calibconv::data::loader::{Dataset, InputSize, LoaderConfig};
use calibconv::data::{BatchSource, CLASSES, IGNORE_LABEL};
use common::{calibconv, calibconv_in};
use tch::Kind;

fn text(o: &Output) -> String {
    format!(
        "{}{}",
        String::from_utf8_lossy(&o.stdout),
        String::from_utf8_lossy(&o.stderr)
    )
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
    let o = synth(&a, &[]);
    assert!(o.status.success(), "{}", text(&o));
    assert!(text(&o).contains("wrote 24 views"), "{}", text(&o));
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
    let o = synth(&b, &[]);
    assert!(o.status.success(), "{}", text(&o));
    let (ta, tb) = (tree(&a), tree(&b));
    assert_eq!(ta.len(), 4 * (2 + 5 * 6));
    assert_eq!(ta, tb);

    // Again in place: nothing to do, nothing changed.
    let o = synth(&a, &[]);
    assert!(
        o.status.success() && text(&o).contains("nothing to do"),
        "{}",
        text(&o)
    );
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
    let args = [
        "synth",
        "--panoramas",
        "3",
        "--pano-height",
        "16",
        "--views-per-panorama",
        "1",
        "--width",
        "16",
        "--out",
    ];
    let o = calibconv(&[&args[..], &[in_root.to_str().unwrap()]].concat());
    assert!(o.status.success(), "{}", text(&o));
    let o = calibconv_in(&elsewhere, &[&args[..], &["out"]].concat());
    assert!(o.status.success(), "{}", text(&o));
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
    assert!(synth(&out, &["--set", "f195"]).status.success());
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
    let o = synth(&out, &["--set", "f195"]);
    assert!(o.status.success(), "{}", text(&o));
    assert!(
        text(&o).contains("wrote 1 views from 1 panoramas"),
        "{}",
        text(&o)
    );
    assert_eq!(tree(&out), before);

    // Another seed or camera width: refused, nothing touched.
    for extra in [&["--seed", "9"][..], &["--width", "20"][..]] {
        let mut args = vec!["--set", "f195"];
        args.extend_from_slice(extra);
        let o = synth(&out, &args);
        assert!(!o.status.success());
        let msg = text(&o);
        assert!(msg.contains("refusing") && msg.contains("--force"), "{msg}");
        assert!(
            msg.contains(&dir.join(MANIFEST).display().to_string()),
            "{msg}"
        );
        assert_eq!(tree(&out), before);
    }
    // A manifest from another generator version: refused by synth and by the loader.
    let old = manifest.replace("\"generator_version\": 1", "\"generator_version\": 0");
    std::fs::write(dir.join(MANIFEST), &old).unwrap();
    let o = synth(&out, &["--set", "f195"]);
    assert!(
        !o.status.success() && text(&o).contains("generator version 0"),
        "{}",
        text(&o)
    );
    let e = Dataset::open(&dir, Split::Train, LoaderConfig::default())
        .unwrap_err()
        .to_string();
    assert!(
        e.contains("manifest.json") && e.contains("version 0"),
        "{e}"
    );
    // --force regenerates (same seed: the same bytes again).
    let o = synth(&out, &["--set", "f195", "--force"]);
    assert!(o.status.success(), "{}", text(&o));
    assert_eq!(tree(&out), before);

    // A non-empty folder that is not a data set.
    let foreign = tmp.path().join("mine");
    std::fs::create_dir_all(foreign.join("f195")).unwrap();
    std::fs::write(foreign.join("f195/notes.txt"), b"keep me").unwrap();
    let o = synth(&foreign, &["--set", "f195"]);
    assert!(
        !o.status.success() && text(&o).contains("without a manifest"),
        "{}",
        text(&o)
    );
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
    let o = calibconv(&[
        "synth",
        "--out",
        out,
        "--kind",
        "rectified",
        "--camera",
        f195,
    ]);
    assert!(!o.status.success());
    assert!(
        text(&o).contains("195") && text(&o).contains("180"),
        "{}",
        text(&o)
    );
    let o = calibconv(&["synth", "--out", out, "--kind", "pers", "--camera", f195]);
    assert!(
        !o.status.success() && text(&o).contains("pinhole"),
        "{}",
        text(&o)
    );
    let o = calibconv(&["synth", "--out", out, "--set", "f999"]);
    assert!(
        !o.status.success() && text(&o).contains("f195"),
        "{}",
        text(&o)
    );
    // --dry-run writes nothing.
    let o = calibconv(&["synth", "--out", out, "--dry-run"]);
    assert!(
        o.status.success() && text(&o).contains("rect-f165"),
        "{}",
        text(&o)
    );
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
    assert!(o.status.success(), "{}", text(&o));
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
    assert_eq!(
        b.depth
            .narrow(2, 14, 2)
            .abs()
            .sum(Kind::Float)
            .double_value(&[]),
        0.0
    );
    assert_eq!(
        b.labels
            .narrow(1, 14, 2)
            .ne(IGNORE_LABEL)
            .any()
            .int64_value(&[]),
        0
    );
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
    let out = tmp.path().join("out");
    let o = calibconv(&[
        "synth",
        "--stanford",
        root.to_str().unwrap(),
        "--pano-height",
        "8",
        "--views-per-panorama",
        "2",
        "--width",
        "16",
        "--set",
        "f195",
        "--out",
        out.to_str().unwrap(),
    ]);
    assert!(o.status.success(), "{}", text(&o));
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
    let o = calibconv(&[
        "synth",
        "--stanford",
        root.to_str().unwrap(),
        "--pano-height",
        "8",
        "--set",
        "f195",
        "--out",
        tmp.path().join("out2").to_str().unwrap(),
    ]);
    assert!(!o.status.success());
    let msg = text(&o);
    assert!(
        msg.contains(&sem.display().to_string()) && msg.contains("index 512"),
        "{msg}"
    );
}
