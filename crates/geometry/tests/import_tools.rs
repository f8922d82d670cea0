//! Other tools' calibration files, imported, against the tools' own models.
//!
//! The files in `tests/golden/calib/` and the rays and pixels of `tests/golden/calib_oracle.json`
//! are written by `tools/make_calib_fixtures.py`: OpenCV's `projectPoints` (radial-tangential,
//! 5 and 8 coefficients) and `fisheye.projectPoints` (Kannala-Brandt), and reference formulas
//! written in Python from the tools' documentation for Mei's model (Kalibr omni-radtan) and the
//! FOV model (Kalibr pinhole-fov, Basalt fov, COLMAP FOV). Each imported camera must project the
//! oracle's rays onto its pixels, unproject then project every pixel of its domain back onto
//! itself, and (pinhole models) report pixels outside the model exactly where the source's
//! distortion folds inside the image.

use std::path::{Path, PathBuf};

use calibconv_geometry::camera::import::{import_file, Format, ImportOptions, Imported};
use calibconv_geometry::camera::{Camera, CameraModel};

/// Projection against the tools' models: both sides evaluate the same float64 formulas, so the
/// difference is round-off (~1e-12 px); 1e-6 px is the bound and far below any formula
/// error (a wrong or dropped coefficient moves pixels by > 1e-3 px).
const ORACLE_PX_TOL: f64 = 1e-6;
/// Unproject then project inside the domain: the inverses stop at residuals below 1e-10
/// normalised units (1e-7 px at these focal lengths) and usually far below; 1e-6 px as above.
const ROUND_TRIP_PX_TOL: f64 = 1e-6;
/// Pixels per side of the round-trip grid.
const GRID: usize = 64;

fn golden(name: &str) -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
        .join("../../tests/golden")
        .join(name)
}

#[derive(serde::Deserialize)]
struct Oracle {
    cases: Vec<Case>,
}

#[derive(serde::Deserialize)]
struct Case {
    file: String,
    format: String,
    camera: Option<usize>,
    fov_deg: Option<f64>,
    model: String,
    folds: bool,
    rays: Vec<[f64; 3]>,
    pixels: Vec<[f64; 2]>,
}

fn import(case: &Case) -> Imported {
    let format: Format = case.format.parse().unwrap();
    let options = ImportOptions {
        camera: case.camera,
        fov_deg: case.fov_deg,
        opencv_model: None,
    };
    let path = golden(&format!("calib/{}", case.file));
    import_file(format, &path, &options)
        .unwrap_or_else(|e| panic!("{} camera {:?}: {e}", case.file, case.camera))
}

fn oracle() -> Oracle {
    let text = std::fs::read_to_string(golden("calib_oracle.json")).unwrap();
    serde_json::from_str(&text).unwrap()
}

#[test]
fn every_tool_projects_like_its_own_model() {
    let oracle = oracle();
    assert_eq!(oracle.cases.len(), 18);
    for case in &oracle.cases {
        let what = format!("{} camera {:?}", case.file, case.camera);
        let imported = import(case);
        let cam = &imported.camera;
        assert_eq!(cam.model_name(), case.model, "{what}");
        let mut worst = 0.0f64;
        for (ray, want) in case.rays.iter().zip(&case.pixels) {
            let got = cam
                .project(*ray)
                .unwrap_or_else(|| panic!("{what}: {ray:?} does not project"));
            worst = worst.max((got[0] - want[0]).hypot(got[1] - want[1]));
        }
        assert!(worst <= ORACLE_PX_TOL, "{what}: {worst} px from the oracle");
        round_trips_inside_the_domain(cam, &what);
        // A pinhole's pixels are outside the model only past a fold (a fisheye's may also lie
        // outside its projection's domain, such as beyond Mei's disc for xi > 1).
        if case.model == "pinhole-radtan" {
            assert_eq!(
                imported.outside > 0.0,
                case.folds,
                "{what}: {}",
                imported.outside
            );
        }
    }
}

/// Every pixel of a grid over the image that unprojects projects back onto itself.
fn round_trips_inside_the_domain(cam: &Camera, what: &str) {
    let [w, h] = cam.size().map(|n| n as f64);
    let mut inside = 0;
    for i in 0..=GRID {
        for j in 0..=GRID {
            let px = [
                -0.5 + w * i as f64 / GRID as f64,
                -0.5 + h * j as f64 / GRID as f64,
            ];
            let Some(ray) = cam.unproject(px) else {
                continue;
            };
            inside += 1;
            let back = cam
                .project(ray)
                .unwrap_or_else(|| panic!("{what}: the ray of {px:?} does not project"));
            let err = (back[0] - px[0]).hypot(back[1] - px[1]);
            assert!(err <= ROUND_TRIP_PX_TOL, "{what} {px:?}: {err} px");
        }
    }
    assert!(
        inside > GRID * GRID / 4,
        "{what}: only {inside} pixels unproject"
    );
}

/// The fold of COLMAP camera 2 (FULL_OPENCV): the import succeeds with its domain, says how much
/// of the image is outside in a note, and the corners are outside while the centre is not.
#[test]
fn a_fold_inside_the_image_imports_with_its_domain() {
    let options = ImportOptions {
        camera: Some(2),
        ..Default::default()
    };
    let path = golden("calib/colmap_full_opencv.txt");
    let imported = import_file(Format::Colmap, &path, &options).unwrap();
    // The fold's image is a circle of ~602 px around the centre of a 1920x1080 image: the
    // fraction outside is 1 - pi 602^2 / (1920 1080) ~ 45 % less what the image edges cut off.
    assert!(
        imported.outside > 0.3 && imported.outside < 0.6,
        "{}",
        imported.outside
    );
    assert!(
        imported
            .notes
            .iter()
            .any(|n| n.contains("outside the model")),
        "{:?}",
        imported.notes
    );
    let cam = &imported.camera;
    assert_eq!(cam.unproject([0.0, 0.0]), None);
    assert!(cam.unproject([960.0, 540.0]).is_some());
    // The field of view ends at the fold: 2 atan(r_fold) with r_fold = 0.941.
    let fov = cam.fov().to_degrees();
    assert!(
        (fov - 2.0 * 0.941f64.atan().to_degrees()).abs() < 0.1,
        "{fov}"
    );
}

/// The same camera, spelt by OpenCV's calibration sample in YAML and in XML, imports the same.
#[test]
fn opencv_yaml_and_xml_of_the_old_sample_are_the_same_camera() {
    let read = |name: &str| {
        let path = golden(&format!("calib/{name}"));
        import_file(Format::OpenCv, &path, &ImportOptions::default())
            .unwrap_or_else(|e| panic!("{name}: {e}"))
            .camera
    };
    let yaml = read("opencv_old_sample.yaml");
    assert_eq!(yaml, read("opencv_old_sample.xml"));
    let Camera::PinholeRadTan(r) = yaml else {
        panic!("{yaml:?}")
    };
    // The file's 6.5746697944293521e+002 and -5.7843597214487474e-001, bit for bit.
    let text = |t: &str| t.parse::<f64>().unwrap();
    assert_eq!(r.fx, text("6.5746697944293521e+002"));
    let k = [
        "-4.1802327176423804e-001",
        "5.0715244063187526e-001",
        "-5.7843597214487474e-001",
    ];
    assert_eq!(r.k, k.map(text));
}

/// `text` imported as `format` from `name` fails naming the file and `field`.
fn refused(format: Format, text: &str, options: &ImportOptions, field: &str, words: &[&str]) {
    let path = Path::new("inline/source.yaml");
    let e = match calibconv_geometry::camera::import::import_text(format, text, path, options) {
        Ok(i) => panic!("imported {:?}", i.camera),
        Err(e) => e,
    };
    let msg = e.to_string();
    assert!(msg.contains("inline/source.yaml"), "{msg}");
    match &e {
        calibconv_geometry::Error::Camera { field: f, .. } => assert_eq!(f, field, "{msg}"),
        other => assert!(field.is_empty(), "expected field {field}: {other:?}"),
    }
    assert!(words.iter().all(|w| msg.contains(w)), "{msg}");
}

#[test]
fn refusals_name_the_file_and_the_field() {
    let read = |name: &str| std::fs::read_to_string(golden(&format!("calib/{name}"))).unwrap();
    let none = ImportOptions::default();
    // A skewed camera matrix (ROS ost.yaml): the entry is named.
    let ros = read("ros_ost.yaml");
    let skewed = ros.replacen(", 0.0, 366.304669", ", 0.75, 366.304669", 1);
    assert_ne!(skewed, ros);
    refused(
        Format::Ros,
        &skewed,
        &none,
        "camera_matrix[0][1]",
        &["skew"],
    );
    refused(
        Format::Ros,
        &ros.replace("plumb_bob", "fisheye_ext"),
        &none,
        "distortion_model",
        &["fisheye_ext"],
    );
    // ORB-SLAM3: an unknown type, a missing coefficient, a second camera that is not there.
    let orb = read("orbslam3_old_pinhole.yaml");
    refused(
        Format::OrbSlam3,
        &orb.replace("\"PinHole\"", "\"Omni\""),
        &none,
        "Camera.type",
        &["Omni"],
    );
    refused(
        Format::OrbSlam3,
        &orb.replace("Camera.k2:", "Camera.k9:"),
        &none,
        "Camera.k2",
        &["missing"],
    );
    let second = ImportOptions {
        camera: Some(1),
        ..Default::default()
    };
    refused(
        Format::OrbSlam3,
        &orb,
        &second,
        "Camera2.fx",
        &["second camera"],
    );
    // ost.txt without its distortion line; OpenCV thin-prism terms.
    let txt = read("ros_ost.txt");
    let broken = txt.replacen("distortion\n", "distortion_x\n", 1);
    refused(
        Format::Ros,
        &broken,
        &none,
        "[narrow_stereo/left] distortion",
        &["missing"],
    );
    let xml = read("opencv_rational.xml");
    let prism = xml.replace("<rows>8</rows>", "<rows>12</rows>").replace(
        "</data></distortion_coefficients>",
        " 0. 0.01 0. 0.</data></distortion_coefficients>",
    );
    refused(
        Format::OpenCv,
        &prism,
        &none,
        "distortion_coefficients[9]",
        &["thin-prism"],
    );
}
