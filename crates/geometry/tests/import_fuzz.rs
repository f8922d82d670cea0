//! The import parsers never panic: arbitrary bytes for every format, and mutations of the valid
//! calibration files of every format (`tests/golden/calib/`), each read with a few option
//! choices. A case either imports or is an error; a panic fails the test and prints the case.
//! Deterministic (a fixed-seed generator), a few thousand cases.

use std::panic::{catch_unwind, AssertUnwindSafe};
use std::path::{Path, PathBuf};

use calibconv_geometry::camera::import::{import_text, Format, ImportOptions};
use calibconv_geometry::camera::CameraModel;

/// Mutated files per fixture file.
const MUTATIONS_PER_FILE: usize = 200;
/// Arbitrary inputs per format.
const ARBITRARY_PER_FORMAT: usize = 150;

/// SplitMix64: small, deterministic, good enough to drive mutations.
struct Rng(u64);

impl Rng {
    fn next(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9e37_79b9_7f4a_7c15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
        z ^ (z >> 31)
    }
    fn below(&mut self, n: usize) -> usize {
        (self.next() % n.max(1) as u64) as usize
    }
}

fn calib_dir() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../../tests/golden/calib")
}

/// Every fixture file with the format that reads it.
fn fixtures() -> Vec<(Format, String)> {
    let mut out = Vec::new();
    for entry in std::fs::read_dir(calib_dir()).unwrap() {
        let path = entry.unwrap().path();
        let name = path.file_name().unwrap().to_string_lossy().into_owned();
        let format = match name.split('_').next().unwrap() {
            "kalibr" => Format::Kalibr,
            "opencv" => Format::OpenCv,
            "basalt" => Format::Basalt,
            "colmap" => Format::Colmap,
            "ocam" => Format::OcamCalib,
            "ros" => Format::Ros,
            "orbslam3" => Format::OrbSlam3,
            other => panic!("{name}: no format for `{other}`"),
        };
        out.push((format, std::fs::read_to_string(&path).unwrap()));
    }
    out.sort_by(|a, b| a.1.cmp(&b.1));
    out
}

/// Tokens that stress number parsing and the models' checks.
const NASTY: [&str; 16] = [
    "nan",
    ".nan",
    "inf",
    "-inf",
    "1e308",
    "-1e308",
    "1e-320",
    "0",
    "-0.0",
    "99999999999",
    "-1",
    "3.5e+002",
    "1.",
    "[",
    "{",
    "\"",
];

/// One random edit of `bytes`.
fn mutate(rng: &mut Rng, bytes: &mut Vec<u8>) {
    let n = bytes.len();
    match rng.below(8) {
        0 if n > 0 => {
            let i = rng.below(n);
            bytes[i] ^= 1 << rng.below(8);
        }
        1 if n > 0 => {
            let i = rng.below(n);
            let len = rng.below(32).min(n - i);
            bytes.drain(i..i + len);
        }
        2 => {
            let i = rng.below(n + 1);
            let extra: Vec<u8> = (0..rng.below(8) + 1).map(|_| rng.next() as u8).collect();
            bytes.splice(i..i, extra);
        }
        3 if n > 0 => {
            let i = rng.below(n);
            let len = rng.below(64).min(n - i);
            let copy = bytes[i..i + len].to_vec();
            let j = rng.below(n + 1);
            bytes.splice(j..j, copy);
        }
        4 => bytes.truncate(rng.below(n + 1)),
        _ => {
            // Replace a number (a run of digits) with a nasty token.
            let digits: Vec<usize> = (0..n).filter(|&i| bytes[i].is_ascii_digit()).collect();
            if digits.is_empty() {
                return;
            }
            let start = digits[rng.below(digits.len())];
            let mut end = start;
            while end < n && (bytes[end].is_ascii_digit() || bytes[end] == b'.') {
                end += 1;
            }
            let token = NASTY[rng.below(NASTY.len())].as_bytes().to_vec();
            bytes.splice(start..end, token);
        }
    }
}

fn options(rng: &mut Rng) -> ImportOptions {
    ImportOptions {
        camera: [None, None, None, None, Some(0), Some(1), Some(2), Some(3)][rng.below(8)],
        fov_deg: [
            None,
            None,
            None,
            None,
            Some(150.0),
            Some(359.0),
            Some(f64::NAN),
        ][rng.below(7)],
        opencv_model: None,
    }
}

/// Imports `text`; a panic fails, naming the case. What imports is exercised a little too.
fn survives(format: Format, text: &str, options: &ImportOptions, what: &str) -> bool {
    let path = Path::new("fuzz/input");
    let result = catch_unwind(AssertUnwindSafe(|| {
        import_text(format, text, path, options).map(|imported| {
            let cam = imported.camera;
            let [w, h] = cam.size();
            let px = [w as f64 / 2.0, h as f64 / 3.0];
            if let Some(ray) = cam.unproject(px) {
                let _ = cam.project(ray);
            }
        })
    }));
    match result {
        Ok(r) => r.is_ok(),
        Err(_) => panic!("{what}: import panicked on {format} input {text:?} with {options:?}"),
    }
}

#[test]
fn mutated_files_of_every_format_never_panic() {
    let mut rng = Rng(47);
    let (mut cases, mut imported) = (0, 0);
    for (format, text) in fixtures() {
        for m in 0..MUTATIONS_PER_FILE {
            let mut bytes = text.clone().into_bytes();
            for _ in 0..rng.below(4) + 1 {
                mutate(&mut rng, &mut bytes);
            }
            let mutated = String::from_utf8_lossy(&bytes).into_owned();
            let opts = options(&mut rng);
            cases += 1;
            imported += usize::from(survives(format, &mutated, &opts, &format!("mutation {m}")));
        }
    }
    // About one mutated file in nine still imports (403 of 3600), so the models' constructors
    // are exercised too.
    assert!(
        cases >= 3000 && imported > cases / 20,
        "{imported} of {cases} imported"
    );
}

#[test]
fn arbitrary_bytes_never_panic() {
    let mut rng = Rng(4747);
    let formats = [
        Format::Kalibr,
        Format::OpenCv,
        Format::Basalt,
        Format::Colmap,
        Format::OcamCalib,
        Format::Ros,
        Format::OrbSlam3,
    ];
    let mut cases = 0;
    for format in formats {
        for i in 0..ARBITRARY_PER_FORMAT {
            let len = rng.below(400);
            // Half printable ASCII with structure characters, half any byte.
            let bytes: Vec<u8> = (0..len)
                .map(|_| {
                    if i % 2 == 0 {
                        b" \n:[]{}<>/-.,0123456789eE#\"abcxyz_"[rng.below(34)]
                    } else {
                        rng.next() as u8
                    }
                })
                .collect();
            let text = String::from_utf8_lossy(&bytes).into_owned();
            let opts = options(&mut rng);
            survives(format, &text, &opts, &format!("arbitrary {i}"));
            cases += 1;
        }
    }
    assert_eq!(cases, 7 * ARBITRARY_PER_FORMAT);
}
