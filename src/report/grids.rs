//! Qualitative grids of a report: per task, block and fisheye data set with both kernels, the
//! first test images' input, ground truth and the two kernels' predictions side by side, from the
//! evaluations' prediction panels ([`crate::eval::visual`]), under a row of column titles; depth
//! grids end with the colour bar of their map (near dark blue to far yellow, per image over
//! `[0, max ground truth]`).

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use image::{Rgb, RgbImage};

use super::collect::Row;
use super::study::{Block, Task, CALIBRATED, STANDARD};
use crate::error::Result;
use crate::eval::visual::{depth_colour, hstack};
use crate::io::write_png_atomic;
use crate::plots::draw_labels;

/// The grids' column titles, left to right.
pub const COLUMNS: [&str; 4] = ["input", "truth", "standard", "calibrated"];
/// Test images a grid shows at most (its rows).
const ROWS: usize = 4;
/// Narrower tiles are enlarged (nearest neighbour, by an integer factor) to at least this width,
/// so that a column is as wide as its title.
const MIN_TILE_WIDTH: u32 = 96;
/// Height of the title row and of the colour bar's strip, in pixels.
const TITLE_HEIGHT: u32 = 22;
const BAR_HEIGHT: u32 = 40;
/// Pixels between tiles and rows (as [`hstack`]).
const GAP: u32 = 2;

fn load_png(path: &Path) -> Option<RgbImage> {
    image::open(path).ok().map(|i| i.to_rgb8())
}

/// Tile `i` of a prediction panel of `n` tiles (tiles separated by 2-pixel gaps, see
/// [`hstack`]).
fn tile(panel: &RgbImage, n: u32, i: u32) -> RgbImage {
    let w = (panel.width() + GAP).saturating_sub(GAP * n) / n;
    image::imageops::crop_imm(panel, i * (w + GAP), 0, w, panel.height()).to_image()
}

/// `img` enlarged by the integer factor that makes it at least [`MIN_TILE_WIDTH`] wide.
fn enlarged(img: RgbImage) -> RgbImage {
    let f = MIN_TILE_WIDTH.div_ceil(img.width().max(1)).max(1);
    if f == 1 {
        return img;
    }
    let (w, h) = (img.width() * f, img.height() * f);
    image::imageops::resize(&img, w, h, image::imageops::FilterType::Nearest)
}

/// One grid row from the standard (`a`) and calibrated (`b`) runs' panels of one test image:
/// input | truth | standard | calibrated. Depth panels are RGB | GT | prediction | error,
/// segmentation panels RGB | GT | prediction.
fn grid_line(a: &RgbImage, b: &RgbImage, task: Task) -> RgbImage {
    let n = if task == Task::Segmentation { 3 } else { 4 };
    let tiles = [tile(a, n, 0), tile(a, n, 1), tile(a, n, 2), tile(b, n, 2)];
    hstack(&tiles.map(enlarged))
}

/// The lines stacked under a row of [`COLUMNS`] titles, with a depth colour bar below for depth.
fn compose(lines: &[RgbImage], task: Task) -> Result<RgbImage> {
    let w = lines.iter().map(|l| l.width()).max().unwrap_or(0);
    let tile_w = (w + GAP) / COLUMNS.len() as u32;
    let bar = if task == Task::Depth { BAR_HEIGHT } else { 0 };
    let h = TITLE_HEIGHT + lines.iter().map(|l| l.height() + GAP).sum::<u32>() + bar;
    let mut grid = RgbImage::from_pixel(w, h, Rgb([255, 255, 255]));
    let mut y = TITLE_HEIGHT;
    for l in lines {
        image::imageops::replace(&mut grid, l, 0, y as i64);
        y += l.height() + GAP;
    }
    let mut labels: Vec<(&str, [i32; 2])> = COLUMNS
        .iter()
        .enumerate()
        .map(|(i, t)| (*t, [(i as u32 * tile_w + 4) as i32, 4]))
        .collect();
    if task == Task::Depth {
        // The colour bar across the grid, under the last row: the depth map from 0 (left) to
        // the image's largest ground-truth depth (right).
        let (x0, x1, top) = (4, w.saturating_sub(4), y + 4);
        for x in x0..x1 {
            let c = Rgb(depth_colour((x - x0) as f32 / (x1 - x0).max(1) as f32));
            for yy in top..top + 10 {
                grid.put_pixel(x, yy, c);
            }
        }
        labels.push(("0 m", [x0 as i32, (top + 12) as i32]));
        let right = "max truth";
        labels.push((right, [x1 as i32 - 56, (top + 12) as i32]));
    }
    draw_labels(&mut grid, &labels, 14)?;
    Ok(grid)
}

/// Qualitative grids for each task, block and fisheye data set with both kernels, from the
/// evaluations' prediction panels of `rows`; `grid_TASK_BLOCK_SET.png` in `out`. Returns the
/// files.
pub fn qualitative_grids(rows: &[&Row], out: &Path) -> Result<Vec<PathBuf>> {
    let mut files = Vec::new();
    let mut groups: BTreeMap<(Task, Block, String), BTreeMap<String, &Row>> = BTreeMap::new();
    for r in rows {
        groups
            .entry((r.cell.task, r.cell.block, r.cell.dataset.clone()))
            .or_default()
            .insert(r.cell.kernel.clone(), r);
    }
    for ((task, block, set), by_kernel) in groups {
        let (Some(std_row), Some(cal_row)) = (by_kernel.get(STANDARD), by_kernel.get(CALIBRATED))
        else {
            continue;
        };
        let mut ids: Vec<PathBuf> = std::fs::read_dir(std_row.dir.join("predictions"))
            .map(|it| it.flatten().map(|e| e.path()).collect())
            .unwrap_or_default();
        ids.sort();
        let mut lines = Vec::new();
        for p in ids.iter().take(ROWS) {
            let Some(name) = p.file_name() else { continue };
            let (Some(a), Some(b)) = (
                load_png(p),
                load_png(&cal_row.dir.join("predictions").join(name)),
            ) else {
                continue;
            };
            lines.push(grid_line(&a, &b, task));
        }
        if lines.is_empty() {
            continue;
        }
        let name = [task.short().to_string(), block.to_string(), set].join("_");
        let file = out.join(format!("grid_{}.png", name.to_lowercase()));
        write_png_atomic(&file, &compose(&lines, task)?)?;
        files.push(file);
    }
    Ok(files)
}
