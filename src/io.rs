//! Atomic file output: write to a temporary file in the destination folder, flush it to the
//! disk, then rename, so an interrupted or failed write (a crash, a full disk, an I/O error)
//! never leaves a truncated file or destroys the previous one. A failed write is an
//! [`Error::Write`] naming the destination.
//!
//! [`stage_bytes`] splits the two halves, for files that must change together (a checkpoint's
//! weights and optimiser state): write every file first, where a full disk shows, then rename
//! them, which takes no space.

use std::io::Write;
use std::path::{Path, PathBuf};

use crate::error::{Error, Result};

/// The temporary file next to `path` (`.NAME.tmp-PID`), its parent folder created.
fn temp_path(path: &Path) -> Result<PathBuf> {
    let parent = match path.parent() {
        Some(p) if !p.as_os_str().is_empty() => p.to_path_buf(),
        _ => PathBuf::from("."),
    };
    std::fs::create_dir_all(&parent).map_err(|e| Error::io(&parent, e))?;
    let name = path
        .file_name()
        .ok_or_else(|| Error::InvalidArgument(format!("{}: not a file path", path.display())))?;
    Ok(parent.join(format!(
        ".{}.tmp-{}",
        name.to_string_lossy(),
        std::process::id()
    )))
}

/// Flushes `tmp` to the disk: where a file system reports a full disk or an I/O error only at
/// `fsync` (network file systems, delayed allocation), it shows here, before the rename.
fn sync_file(tmp: &Path, path: &Path) -> Result<()> {
    std::fs::File::open(tmp)
        .and_then(|f| f.sync_all())
        .map_err(|e| write_error(path, e))
}

/// An [`Error::Write`] of `path`.
fn write_error(path: &Path, error: std::io::Error) -> Error {
    Error::Write {
        path: path.to_path_buf(),
        error,
    }
}

/// A file written in full next to its destination, not yet in place: [`Staged::commit`]
/// renames it onto the destination; dropped uncommitted, it is removed.
#[derive(Debug)]
pub struct Staged {
    tmp: PathBuf,
    path: PathBuf,
}

impl Staged {
    /// Puts the file in place (a rename within one folder).
    pub fn commit(self) -> Result<()> {
        std::fs::rename(&self.tmp, &self.path).map_err(|e| write_error(&self.path, e))
    }

    /// The destination.
    pub fn path(&self) -> &Path {
        &self.path
    }
}

impl Drop for Staged {
    fn drop(&mut self) {
        // After a commit the temporary file no longer exists; this is then a no-op.
        let _ = std::fs::remove_file(&self.tmp);
    }
}

/// Writes `bytes` to a temporary file next to `path` and flushes it; nothing replaces `path`
/// until [`Staged::commit`]. On error nothing is left behind and `path` is untouched.
pub fn stage_bytes(path: &Path, bytes: &[u8]) -> Result<Staged> {
    let staged = Staged {
        tmp: temp_path(path)?,
        path: path.to_path_buf(),
    };
    std::fs::File::create(&staged.tmp)
        .and_then(|mut f| {
            f.write_all(bytes)?;
            f.sync_all()
        })
        .map_err(|e| write_error(path, e))?;
    Ok(staged)
}

/// Runs `write` on a temporary path next to `path` and flushes the file; nothing replaces
/// `path` until [`Staged::commit`]. The parent folder is created if needed. On error the
/// temporary file is removed and `path` is untouched.
pub fn stage_with(path: &Path, write: impl FnOnce(&Path) -> Result<()>) -> Result<Staged> {
    let staged = Staged {
        tmp: temp_path(path)?,
        path: path.to_path_buf(),
    };
    write(&staged.tmp)?;
    sync_file(&staged.tmp, path)?;
    Ok(staged)
}

/// [`stage_with`], then [`Staged::commit`]: `path` is replaced in one rename, or not at all.
pub fn write_atomic(path: &Path, write: impl FnOnce(&Path) -> Result<()>) -> Result<()> {
    stage_with(path, write)?.commit()
}

/// An I/O error while writing `path` (for writers other than [`stage_bytes`]).
pub fn write_failed(path: &Path, error: std::io::Error) -> Error {
    write_error(path, error)
}

/// [`write_atomic`] for bytes already in memory.
pub fn write_bytes_atomic(path: &Path, bytes: &[u8]) -> Result<()> {
    stage_bytes(path, bytes)?.commit()
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

    #[test]
    fn staged_files_replace_their_destination_only_when_committed() {
        let dir = tempfile::tempdir().unwrap();
        let (a, b) = (dir.path().join("a"), dir.path().join("b"));
        write_bytes_atomic(&a, b"a1").unwrap();
        let staged = stage_bytes(&a, b"a2").unwrap();
        assert_eq!(std::fs::read(&a).unwrap(), b"a1");
        drop(staged);
        assert_eq!(std::fs::read(&a).unwrap(), b"a1");
        assert_eq!(std::fs::read_dir(dir.path()).unwrap().count(), 1);
        let (sa, sb) = (
            stage_bytes(&a, b"a3").unwrap(),
            stage_bytes(&b, b"b1").unwrap(),
        );
        sa.commit().unwrap();
        sb.commit().unwrap();
        assert_eq!(std::fs::read(&a).unwrap(), b"a3");
        assert_eq!(std::fs::read(&b).unwrap(), b"b1");
        assert_eq!(std::fs::read_dir(dir.path()).unwrap().count(), 2);
    }
}
