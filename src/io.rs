//! Atomic file output: write to a temporary file in the destination folder, then rename, so an
//! interrupted or failed write never leaves a truncated file or destroys the previous one.

use std::path::{Path, PathBuf};

use crate::error::{Error, Result};

/// Runs `write` on a temporary path next to `path`, then renames it onto `path`. The parent
/// folder is created if needed. On error the temporary file is removed and `path` is untouched.
pub fn write_atomic(path: &Path, write: impl FnOnce(&Path) -> Result<()>) -> Result<()> {
    let parent = match path.parent() {
        Some(p) if !p.as_os_str().is_empty() => p.to_path_buf(),
        _ => PathBuf::from("."),
    };
    std::fs::create_dir_all(&parent).map_err(|e| Error::io(&parent, e))?;
    let name = path
        .file_name()
        .ok_or_else(|| Error::InvalidArgument(format!("{}: not a file path", path.display())))?;
    let tmp = parent.join(format!(
        ".{}.tmp-{}",
        name.to_string_lossy(),
        std::process::id()
    ));
    let result =
        write(&tmp).and_then(|()| std::fs::rename(&tmp, path).map_err(|e| Error::io(path, e)));
    if result.is_err() {
        let _ = std::fs::remove_file(&tmp);
    }
    result
}

/// [`write_atomic`] for bytes already in memory.
pub fn write_bytes_atomic(path: &Path, bytes: &[u8]) -> Result<()> {
    write_atomic(path, |tmp| {
        std::fs::write(tmp, bytes).map_err(|e| Error::io(tmp, e))
    })
}

/// Encodes `img` as PNG and writes it atomically; an encoding failure is an [`Error::Image`]
/// naming `path`. Figures are written once and committed (docs/study/), so they get the best
/// compression, with the smaller of two filterings: none (plots of flat colours: 3-4x smaller
/// than the default encoding) and adaptive (pictures).
pub fn write_png_atomic(path: &Path, img: &image::RgbImage) -> Result<()> {
    use image::codecs::png::{CompressionType, FilterType, PngEncoder};
    let encode = |filter| {
        let mut bytes = Vec::new();
        let encoder = PngEncoder::new_with_quality(&mut bytes, CompressionType::Best, filter);
        img.write_with_encoder(encoder)
            .map(|()| bytes)
            .map_err(|e| Error::Image {
                path: path.to_path_buf(),
                message: e.to_string(),
            })
    };
    let flat = encode(FilterType::NoFilter)?;
    let adaptive = encode(FilterType::Adaptive)?;
    let bytes = if flat.len() <= adaptive.len() {
        flat
    } else {
        adaptive
    };
    write_bytes_atomic(path, &bytes)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn png_figures_round_trip_and_flat_plots_are_small() {
        let dir = tempfile::tempdir().unwrap();
        // A plot-like image (flat colours, a line) and a noisy one: both decode to themselves.
        let plot = image::RgbImage::from_fn(300, 200, |x, y| {
            if (y as i64 - 100).abs() == (x as i64 / 3 - 50).abs() {
                image::Rgb([31, 119, 180])
            } else {
                image::Rgb([255, 255, 255])
            }
        });
        let noise = image::RgbImage::from_fn(64, 64, |x, y| {
            let h = (x * 2_654_435_761u32) ^ (y * 40_503);
            image::Rgb([h as u8, (h >> 8) as u8, (h >> 16) as u8])
        });
        for (name, img) in [("plot.png", &plot), ("noise.png", &noise)] {
            let path = dir.path().join(name);
            write_png_atomic(&path, img).unwrap();
            assert_eq!(&image::open(&path).unwrap().to_rgb8(), img, "{name}");
        }
        let size = std::fs::metadata(dir.path().join("plot.png"))
            .unwrap()
            .len();
        assert!(size < 8_000, "{size} bytes for a 300x200 two-colour plot");
    }

    #[test]
    fn failed_write_keeps_the_old_file() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("out.txt");
        write_bytes_atomic(&path, b"first").unwrap();
        let err = write_atomic(&path, |tmp| {
            std::fs::write(tmp, b"partial").unwrap();
            Err(Error::InvalidArgument("boom".into()))
        });
        assert!(err.is_err());
        assert_eq!(std::fs::read(&path).unwrap(), b"first");
        // No temporary file left behind.
        assert_eq!(std::fs::read_dir(dir.path()).unwrap().count(), 1);
    }
}
