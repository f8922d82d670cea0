//! `calibconv camera import`: other tools' calibration files as camera files.
//!
//! Fixtures: small hand-written files in each tool's format in `tests/golden/calib/` (see
//! `tests/golden/README.md`). Where a fixture holds the same camera as a shipped camera file
//! (`data/cameras/`), the import must equal it exactly: every conversion (COLMAP's half-pixel
//! shift, OCamCalib's row/column order, Kalibr's intrinsics order) is checked to the bit.

use std::path::{Path, PathBuf};
use std::process::Output;

use calibconv::camera::import::{
    import_file, import_text, Format, FovSource, ImportOptions, Imported, OpenCvModel,
};
use calibconv::camera::{self, Camera, CameraModel};

use crate::common::{self, assert_contains, calibconv, failed, golden, ok, s};

/// Two closed forms of Mei's projection in float64: round-off only (~1e-13 px at these radii).
const MEI_PX_TOL: f64 = 1e-9;

fn calib(name: &str) -> PathBuf {
    golden(&format!("calib/{name}"))
}

fn shipped(name: &str) -> Camera {
    let path = PathBuf::from(env!("CARGO_MANIFEST_DIR"))
        .join("data/cameras")
        .join(name);
    camera::load(&path).unwrap_or_else(|e| panic!("{}: {e}", path.display()))
}

fn import(format: Format, name: &str, camera: Option<usize>, fov_deg: Option<f64>) -> Imported {
    let options = ImportOptions {
        camera,
        fov_deg,
        opencv_model: None,
    };
    import_file(format, &calib(name), &options)
        .unwrap_or_else(|e| panic!("{name} camera {camera:?}: {e}"))
}

fn import_err(format: Format, name: &str, camera: Option<usize>) -> String {
    let options = ImportOptions {
        camera,
        ..Default::default()
    };
    match import_file(format, &calib(name), &options) {
        Ok(i) => panic!("{name} camera {camera:?} imported: {:?}", i.camera),
        Err(e) => e.to_string(),
    }
}

#[test]
fn kalibr_camchain_models() {
    // cam0: pinhole-equi, field of view from the image width.
    let cam0 = import(Format::Kalibr, "kalibr_camchain.yaml", None, None);
    assert_eq!(cam0.fov, FovSource::ImageWidth);
    let Camera::KannalaBrandt(kb) = &cam0.camera else {
        panic!("{:?}", cam0.camera)
    };
    assert_eq!(
        [kb.fx, kb.fy, kb.cx, kb.cy],
        [
            190.97847715128717,
            190.9733070521226,
            254.93170605935475,
            256.8974428996504
        ]
    );
    assert_eq!(kb.k[3], 0.00020293673591811182);
    // The edges (-0.5, cy) and (511.5, cy) are ~255.4 and ~256.6 px from the centre.
    let edge = |u: f64| {
        let r = cam0.camera.unproject([u, kb.cy]).unwrap();
        r[0].hypot(r[1]).atan2(r[2]).to_degrees()
    };
    let want = edge(-0.5) + edge(511.5);
    assert!(
        kb.fov_deg <= want && want - kb.fov_deg < 1e-3,
        "{} vs {want}",
        kb.fov_deg
    );
    assert!(cam0.source.contains("cam0") && cam0.source.contains("pinhole-equi"));

    // cam1: pinhole-radtan (EuRoC cam0) is the shipped example, k3 = 0.
    let cam1 = import(Format::Kalibr, "kalibr_camchain.yaml", Some(1), None);
    assert_eq!(cam1.camera, shipped("radtan_example.toml"));
    assert_eq!(cam1.fov, FovSource::Derived);
    // cam2: ds [xi, alpha, fu, fv, pu, pv]; cam3: eucm [alpha, beta, fu, fv, pu, pv].
    let cam2 = import(Format::Kalibr, "kalibr_camchain.yaml", Some(2), Some(153.4));
    assert_eq!(cam2.camera, shipped("ds_example.toml"));
    let cam3 = import(Format::Kalibr, "kalibr_camchain.yaml", Some(3), Some(190.0));
    assert_eq!(cam3.camera, shipped("eucm_example.toml"));
}

#[test]
fn kalibr_omni_is_the_unified_model() {
    // cam4: omni [xi, fu, fv, pu, pv] = [0.9, 350, 349, 320.5, 240.25] with zero radtan.
    let cam4 = import(Format::Kalibr, "kalibr_camchain.yaml", Some(4), Some(180.0));
    let Camera::Unified(u) = &cam4.camera else {
        panic!("{:?}", cam4.camera)
    };
    assert_eq!(u.alpha, 0.9 / 1.9);
    // Mei's projection as Kalibr writes it: u = fu x / (z + xi |p|) + pu.
    let (xi, fu, fv, pu, pv) = (0.9, 350.0, 349.0, 320.5, 240.25);
    let rays: [[f64; 3]; 4] = [
        [0.1, -0.2, 1.0],
        [1.0, 0.5, 0.2],
        [-2.0, 0.3, -0.4],
        [0.0, 0.0, 3.0],
    ];
    for p in rays {
        let d = (p[0] * p[0] + p[1] * p[1] + p[2] * p[2]).sqrt();
        let mei = [
            fu * p[0] / (p[2] + xi * d) + pu,
            fv * p[1] / (p[2] + xi * d) + pv,
        ];
        let ours = u.project(p).unwrap();
        let err = (ours[0] - mei[0]).hypot(ours[1] - mei[1]);
        assert!(err < MEI_PX_TOL, "{p:?}: {ours:?} vs Mei {mei:?}");
    }
}

#[test]
fn opencv_filestorage_yaml_fisheye_is_f195() {
    let f195 = import(Format::OpenCv, "opencv_fisheye.yaml", None, Some(195.0));
    assert_eq!(f195.camera, shipped("f195.toml"));
    assert_eq!(f195.fov, FovSource::Given);
    // Without --fov-deg the image width decides: F195's image circle (~976 px) is narrower than
    // its 1080 px width, so that angle (~216 deg) exceeds the lens's 195 (the documented caveat).
    let wide = import(Format::OpenCv, "opencv_fisheye.yaml", None, None);
    let fov = wide.camera.fov().to_degrees();
    assert!(fov > 210.0 && fov < 220.0, "{fov}");
}

#[test]
fn opencv_filestorage_json_standard_is_euroc() {
    let euroc = import(Format::OpenCv, "opencv_standard.json", None, None);
    assert_eq!(euroc.camera, shipped("radtan_example.toml"));
    assert!(euroc.source.contains("standard"));
}

const AMBIGUOUS: &str = "\
%YAML:1.0
---
image_width: 640
image_height: 480
camera_matrix: !!opencv-matrix
   rows: 3
   cols: 3
   dt: d
   data: [ 300., 0., 320., 0., 300., 240., 0., 0., 1. ]
distortion_coefficients: !!opencv-matrix
   rows: 1
   cols: 4
   dt: d
   data: [ -0.1, 0.01, 0., 0. ]
";

#[test]
fn opencv_four_coefficients_need_the_model() {
    let path = Path::new("inline/ambiguous.yaml");
    let e = import_text(Format::OpenCv, AMBIGUOUS, path, &ImportOptions::default()).unwrap_err();
    let msg = e.to_string();
    assert!(
        msg.contains("--opencv-model") && msg.contains("inline/ambiguous.yaml"),
        "{msg}"
    );
    let with = |m| ImportOptions {
        opencv_model: Some(m),
        fov_deg: (m == OpenCvModel::Fisheye).then_some(150.0),
        ..Default::default()
    };
    let standard = import_text(
        Format::OpenCv,
        AMBIGUOUS,
        path,
        &with(OpenCvModel::Standard),
    );
    let Camera::PinholeRadTan(r) = standard.unwrap().camera else {
        panic!("not radtan")
    };
    assert_eq!((r.k, r.p), ([-0.1, 0.01, 0.0], [0.0, 0.0]));
    let fisheye = import_text(Format::OpenCv, AMBIGUOUS, path, &with(OpenCvModel::Fisheye));
    let Camera::KannalaBrandt(k) = fisheye.unwrap().camera else {
        panic!("not Kannala-Brandt")
    };
    assert_eq!(k.k, [-0.1, 0.01, 0.0, 0.0]);
    // The rational model (8 coefficients) reads; thin-prism terms are refused, naming them.
    let rational = AMBIGUOUS.replace("cols: 4", "cols: 8").replace(
        "[ -0.1, 0.01, 0., 0. ]",
        "[ -0.1, 0.01, 0., 0., 0., 0.2, 0., 0. ]",
    );
    let imported = import_text(Format::OpenCv, &rational, path, &ImportOptions::default());
    let Camera::PinholeRadTan(r) = imported.unwrap().camera else {
        panic!("not radtan")
    };
    assert_eq!((r.k, r.k_den), ([-0.1, 0.01, 0.0], [0.2, 0.0, 0.0]));
    let prism = AMBIGUOUS.replace("cols: 4", "cols: 12").replace(
        "[ -0.1, 0.01, 0., 0. ]",
        "[ -0.1, 0.01, 0., 0., 0., 0., 0., 0., 0.003, 0., 0., 0. ]",
    );
    let e = import_text(Format::OpenCv, &prism, path, &ImportOptions::default()).unwrap_err();
    assert_contains(
        &e.to_string(),
        &["thin-prism", "distortion_coefficients[8]"],
    );
    // Skew is refused, naming the entry.
    let skew = AMBIGUOUS.replace("[ 300., 0., 320.", "[ 300., 0.5, 320.");
    let e = import_text(Format::OpenCv, &skew, path, &with(OpenCvModel::Standard)).unwrap_err();
    assert_contains(&e.to_string(), &["skew", "camera_matrix[0][1]"]);
}

/// The cameras of the Basalt and COLMAP fixtures that are shipped camera files.
#[test]
fn basalt_and_colmap_cameras_are_the_shipped_files() {
    let (basalt, colmap) = ("basalt_calibration.json", "colmap_cameras.txt");
    for (format, name, camera, fov_deg, file) in [
        (Format::Basalt, basalt, None, Some(153.4), "ds_example.toml"),
        (Format::Basalt, basalt, Some(1), Some(195.0), "f195.toml"),
        (
            Format::Basalt,
            basalt,
            Some(2),
            Some(190.0),
            "eucm_example.toml",
        ),
        (
            Format::Basalt,
            basalt,
            Some(3),
            Some(185.0),
            "ucm_example.toml",
        ),
        (Format::Basalt, basalt, Some(4), None, "pers.toml"),
        (Format::Colmap, colmap, Some(2), None, "radtan_example.toml"),
        (Format::Colmap, colmap, Some(6), None, "radtan_example.toml"),
        (Format::Colmap, colmap, Some(3), None, "pers.toml"),
        (Format::Colmap, colmap, Some(4), None, "pers.toml"),
    ] {
        let imported = import(format, name, camera, fov_deg).camera;
        assert_eq!(imported, shipped(file), "{name} camera {camera:?}");
    }
}

/// The models these fixtures once held as unsupported examples: Kalibr pinhole-fov and
/// omni-radtan, Basalt pinhole-radtan8, COLMAP FOV (their projections are checked against
/// the tools' models in crates/geometry/tests/import_tools.rs).
#[test]
fn fov_mei_and_rational_models_import() {
    let kalibr = "kalibr_camchain.yaml";
    let Camera::Fov(fov) = import(Format::Kalibr, kalibr, Some(5), None).camera else {
        panic!("cam5 is not fov")
    };
    assert_eq!((fov.w, fov.fx, fov.cx), (0.93, 300.0, 320.0));
    let Camera::Mei(mei) = import(Format::Kalibr, kalibr, Some(6), Some(180.0)).camera else {
        panic!("cam6 is not mei")
    };
    assert_eq!(
        (mei.xi, mei.fx, mei.k, mei.p),
        (0.9, 350.0, [-0.1, 0.02], [0.0, 0.0])
    );
    let basalt = import(Format::Basalt, "basalt_calibration.json", Some(5), None).camera;
    let Camera::PinholeRadTan(r8) = basalt else {
        panic!("{basalt:?}")
    };
    assert_eq!((r8.k, r8.rpmax), ([0.1, 0.0, 0.0], 2.0));
    let colmap = import(Format::Colmap, "colmap_cameras.txt", Some(7), None).camera;
    let Camera::Fov(fov) = colmap else {
        panic!("{colmap:?}")
    };
    // COLMAP's centre of the top-left pixel is (0.5, 0.5).
    assert_eq!((fov.w, fov.cx, fov.cy), (0.9, 319.5, 239.5));
}

/// Models no camera file can hold, and cameras a file does not have: errors naming them.
#[test]
fn unsupported_models_and_missing_cameras_are_named() {
    let kalibr = "kalibr_camchain.yaml";
    let (basalt, colmap) = ("basalt_calibration.json", "colmap_cameras.txt");
    for (format, name, camera, parts) in [
        (
            Format::Kalibr,
            kalibr,
            9,
            &["cam9", "cam0", "kalibr_camchain.yaml"][..],
        ),
        (Format::Basalt, basalt, 6, &["6 camera(s)"]),
        (Format::Colmap, colmap, 42, &["CAMERA_ID 42"]),
    ] {
        assert_contains(&import_err(format, name, Some(camera)), parts);
    }
    let path = Path::new("inline/unsupported");
    for (format, text, parts) in [
        (
            Format::Kalibr,
            "cam0:\n  camera_model: ds\n  distortion_model: radtan\n  intrinsics: [0, 0.5, 1, 1, 1, 1]\n  distortion_coeffs: [0.1, 0, 0, 0]\n  resolution: [64, 48]\n",
            &["`ds-radtan`", "not supported", "cam0.camera_model"][..],
        ),
        (
            Format::Colmap,
            "1 THIN_PRISM_FISHEYE 64 48 1 1 1 1 0 0 0 0 0 0 0 0 0 0\n",
            &["`THIN_PRISM_FISHEYE`", "not supported"],
        ),
        (
            Format::Basalt,
            r#"{"value0": {"intrinsics": [{"camera_type": "bal", "intrinsics": {"fx": 1.0}}], "resolution": [[64, 48]]}}"#,
            &["`bal`", "not supported"],
        ),
    ] {
        let e = import_text(format, text, path, &ImportOptions::default()).unwrap_err();
        assert_contains(&e.to_string(), &[&["inline/unsupported"][..], parts].concat());
    }
}

#[test]
fn colmap_cameras_txt_models_and_half_pixel_centres() {
    let file = "colmap_cameras.txt";
    // The first line by default; COLMAP's 540.5, 480.5 is our 540, 480.
    let fisheye = import(Format::Colmap, file, None, Some(195.0));
    assert_eq!(fisheye.camera, shipped("f195.toml"));
    assert!(fisheye.notes.iter().any(|n| n.contains("0.5")));
    let Camera::PinholeRadTan(radial) = import(Format::Colmap, file, Some(5), None).camera else {
        panic!("SIMPLE_RADIAL is not radtan")
    };
    assert_eq!(
        (radial.fx, radial.cx, radial.cy, radial.k),
        (500.0, 319.5, 239.5, [-0.1, 0.0, 0.0])
    );
}

#[test]
fn ocamcalib_calib_results_is_the_example_with_rows_and_columns_swapped() {
    let ocam = import(
        Format::OcamCalib,
        "ocam_calib_results.txt",
        None,
        Some(190.0),
    );
    assert_eq!(ocam.camera, shipped("ocam_example.toml"));
    // Without --fov-deg: the image width (the polynomial is valid that far).
    let wide = import(Format::OcamCalib, "ocam_calib_results.txt", None, None);
    assert_eq!(wide.fov, FovSource::ImageWidth);
    // A count that does not match its coefficients names the line.
    let text = std::fs::read_to_string(calib("ocam_calib_results.txt")).unwrap();
    let broken = text.replacen("5 -1.810000e+02", "6 -1.810000e+02", 1);
    let e = import_text(
        Format::OcamCalib,
        &broken,
        Path::new("calib_results.txt"),
        &ImportOptions::default(),
    )
    .unwrap_err();
    assert!(
        e.to_string().contains("line 3") && e.to_string().contains("direct polynomial"),
        "{e}"
    );
}

#[test]
fn options_that_do_not_apply_are_errors() {
    let pinhole_fov = import_file(
        Format::Colmap,
        &calib("colmap_cameras.txt"),
        &ImportOptions {
            camera: Some(3),
            fov_deg: Some(90.0),
            ..Default::default()
        },
    )
    .unwrap_err();
    assert!(
        pinhole_fov.to_string().contains("--fov-deg"),
        "{pinhole_fov}"
    );
    let camera_opencv = import_err(Format::OpenCv, "opencv_standard.json", Some(1));
    assert!(camera_opencv.contains("--camera"), "{camera_opencv}");
}

#[test]
fn an_image_edge_outside_the_model_asks_for_the_field_of_view() {
    // alpha > 0.5 with a short focal length: the image edges lie beyond the projection's fold.
    let text = "cam0:\n  camera_model: eucm\n  distortion_model: none\n  \
                intrinsics: [0.7, 1.0, 100.0, 100.0, 320.0, 240.0]\n  resolution: [640, 480]\n";
    let path = Path::new("camchain.yaml");
    let e = import_text(Format::Kalibr, text, path, &ImportOptions::default()).unwrap_err();
    assert!(e.to_string().contains("--fov-deg"), "{e}");
    let options = ImportOptions {
        fov_deg: Some(180.0),
        ..Default::default()
    };
    assert!(import_text(Format::Kalibr, text, path, &options).is_ok());
}

#[test]
fn cli_writes_a_camera_file_that_reads_back() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("euroc.toml");
    let source = calib("kalibr_camchain.yaml");
    ok(import_cli("kalibr", &source, "1", &out));
    assert_eq!(camera::load(&out).unwrap(), shipped("radtan_example.toml"));
    let text = std::fs::read_to_string(&out).unwrap();
    assert!(
        text.starts_with("# Written by `calibconv camera import --from kalibr`"),
        "{text}"
    );
    assert!(text.contains("name = \"euroc\""), "{text}");
    // The written file works with the other commands.
    let png = dir.path().join("k.png");
    ok(calibconv(&[
        "kernels",
        "--camera",
        s(&out),
        "--out",
        s(&png),
    ]));
}

/// `calibconv camera import --from FORMAT SOURCE --camera CAMERA --out OUT`.
fn import_cli(format: &str, source: &Path, camera: &str, out: &Path) -> Output {
    let from = ["camera", "import", "--from", format, s(source)];
    calibconv(&[&from[..], &["--camera", camera, "--out", s(out)]].concat())
}

#[test]
fn cli_unsupported_model_fails_naming_it_and_writes_nothing() {
    let dir = tempfile::tempdir().unwrap();
    let source = dir.path().join("cameras.txt");
    std::fs::write(
        &source,
        "7 THIN_PRISM_FISHEYE 64 48 1 1 1 1 0 0 0 0 0 0 0 0 0 0\n",
    )
    .unwrap();
    let out = dir.path().join("prism.toml");
    let err = failed(import_cli("colmap", &source, "7", &out));
    assert_contains(&err, &["`THIN_PRISM_FISHEYE`", "cameras.txt"]);
    assert!(!out.exists());
    assert_eq!(std::fs::read_dir(dir.path()).unwrap().count(), 1);
    // An unknown source format is a usage error listing the formats.
    let err = failed(calibconv(&[
        "camera", "import", "--from", "matlab", "x", "--out", "y.toml",
    ]));
    assert_contains(&err, &["ocamcalib", "ros", "orbslam3"]);
}

/// `--from ros` and `--from orbslam3` with `--camera 1`: the second camera, with its own
/// coefficients, as a camera file that reads back.
#[test]
fn cli_ros_and_orbslam3_second_cameras() {
    let dir = tempfile::tempdir().unwrap();
    for (from, file, want_fx) in [
        ("ros", "ros_ost.txt", 457.59),
        ("orbslam3", "orbslam3_kb8_stereo.yaml", 190.442369),
    ] {
        let out = dir.path().join(format!("{from}.toml"));
        let stdout = common::stdout(&ok(import_cli(from, &calib(file), "1", &out)));
        assert!(stdout.contains(from), "{stdout}");
        let cam = camera::load(&out).unwrap();
        let fx = match &cam {
            Camera::PinholeRadTan(m) => m.fx,
            Camera::KannalaBrandt(m) => m.fx,
            other => panic!("{other:?}"),
        };
        assert_eq!(fx, want_fx, "{file}");
        let text = std::fs::read_to_string(&out).unwrap();
        assert!(text.contains(&format!("--from {from}")), "{text}");
    }
}

/// A COLMAP FULL_OPENCV camera whose distortion folds inside the image imports; the written
/// file's header and the command's output say how much of the image is outside the model.
#[test]
fn cli_folding_camera_reports_the_image_outside() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("fold.toml");
    let stdout = common::stdout(&ok(import_cli(
        "colmap",
        &calib("colmap_full_opencv.txt"),
        "2",
        &out,
    )));
    assert!(stdout.contains("outside the model"), "{stdout}");
    let text = std::fs::read_to_string(&out).unwrap();
    assert!(
        text.contains("% of the image lies outside the model"),
        "{text}"
    );
    let cam = camera::load(&out).unwrap();
    assert_eq!(cam.unproject([0.0, 0.0]), None);
}
