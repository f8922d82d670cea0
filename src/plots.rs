//! Line plots with one-standard-deviation bands (the paper's radial plots, Figures 3 and 5),
//! rendered with plotters into PNG.
//!
//! Text uses the DejaVu Sans font embedded from `data/fonts/` (licence beside it), so plots look
//! the same on every machine, fonts installed or not.

use std::path::Path;
use std::sync::Once;

use plotters::prelude::*;
use plotters::style::{register_font, FontStyle};

use crate::error::{Error, Result};
use crate::io::write_png_atomic;

/// Colour of standard kernels in every figure (the paper's red).
pub const STANDARD_RED: [u8; 3] = [214, 39, 40];
/// Colour of calibrated kernels in every figure (the paper's blue).
pub const CALIBRATED_BLUE: [u8; 3] = [31, 119, 180];
/// Colour of the rectified-image baseline.
pub const RECTIFIED_GREEN: [u8; 3] = [44, 160, 44];
/// CAM-Convs (`camconv`).
pub const CAMCONV_ORANGE: [u8; 3] = [255, 127, 14];
/// Calibrated offsets that keep learning (`calibrated-learned`).
pub const LEARNED_PURPLE: [u8; 3] = [148, 103, 189];

static FONT: &[u8] = include_bytes!("../data/fonts/DejaVuSans.ttf");

fn ensure_font() {
    static REGISTER: Once = Once::new();
    REGISTER.call_once(|| {
        // The embedded file is a valid TrueType font; failure here is a build defect.
        if register_font("sans-serif", FontStyle::Normal, FONT).is_err() {
            panic!("embedded DejaVuSans.ttf failed to load");
        }
    });
}

/// One curve: `mean[i] +- std[i]` at `x[i]`.
#[derive(Clone, Debug)]
pub struct Curve {
    pub label: String,
    pub colour: [u8; 3],
    pub x: Vec<f64>,
    pub mean: Vec<f64>,
    /// One standard deviation; empty for no band.
    pub std: Vec<f64>,
}

impl Curve {
    /// The curve through `(x, mean, interval)` points, its band each interval `[lo, hi]`
    /// (centred on the mean: half-width `(hi - lo) / 2`); no band unless every point has an
    /// interval.
    pub fn with_intervals(
        label: String,
        colour: [u8; 3],
        points: impl IntoIterator<Item = (f64, f64, Option<[f64; 2]>)>,
    ) -> Curve {
        let (x, mean, intervals): (Vec<f64>, Vec<f64>, Vec<Option<[f64; 2]>>) =
            points.into_iter().collect();
        let std = if intervals.iter().all(Option::is_some) {
            intervals
                .iter()
                .flatten()
                .map(|[lo, hi]| (hi - lo) / 2.0)
                .collect()
        } else {
            Vec::new()
        };
        Curve {
            label,
            colour,
            x,
            mean,
            std,
        }
    }
}

/// Titles and size of a plot.
#[derive(Clone, Debug)]
pub struct PlotSpec {
    pub title: String,
    pub x_label: String,
    pub y_label: String,
    /// `[width, height]` in pixels.
    pub size: [u32; 2],
}

impl Default for PlotSpec {
    fn default() -> Self {
        PlotSpec {
            title: String::new(),
            x_label: String::new(),
            y_label: String::new(),
            size: [800, 500],
        }
    }
}

fn plot_err(path: &Path, e: impl std::fmt::Display) -> Error {
    Error::Image {
        path: path.to_path_buf(),
        message: format!("plotting failed: {e}"),
    }
}

/// Writes `labels` (text, top-left corner `[x, y]` in pixels) in black, `size` pixels high, onto
/// `img` with the embedded font (titles and legends of composed figures).
pub fn draw_labels(
    img: &mut image::RgbImage,
    labels: &[(&str, [i32; 2])],
    size: u32,
) -> Result<()> {
    ensure_font();
    let (w, h) = img.dimensions();
    let err = |e: &dyn std::fmt::Display| Error::InvalidArgument(format!("drawing text: {e}"));
    let root = BitMapBackend::with_buffer(img.as_mut(), (w, h)).into_drawing_area();
    let style = ("sans-serif", size as f64).into_font().color(&BLACK);
    for (text, [x, y]) in labels {
        root.draw(&Text::new(*text, (*x, *y), style.clone()))
            .map_err(|e| err(&e))?;
    }
    root.present().map_err(|e| err(&e))
}

/// Draws `curves` (mean line + translucent one-std band each) and writes a PNG atomically.
/// Non-finite values are skipped; the y range covers every band.
pub fn line_band_plot(path: &Path, spec: &PlotSpec, curves: &[Curve]) -> Result<()> {
    ensure_font();
    for c in curves {
        if c.x.len() != c.mean.len() || (!c.std.is_empty() && c.std.len() != c.x.len()) {
            return Err(Error::InvalidArgument(format!(
                "curve `{}`: x, mean and std must have the same length",
                c.label
            )));
        }
    }
    let points = |c: &Curve| -> Vec<(f64, f64, f64)> {
        (0..c.x.len())
            .map(|i| (c.x[i], c.mean[i], c.std.get(i).copied().unwrap_or(0.0)))
            .filter(|(x, m, s)| x.is_finite() && m.is_finite() && s.is_finite())
            .collect()
    };
    let all: Vec<(f64, f64, f64)> = curves.iter().flat_map(points).collect();
    if all.is_empty() {
        return Err(Error::InvalidArgument(format!(
            "{}: nothing to plot (no finite points)",
            path.display()
        )));
    }
    let (mut x0, mut x1, mut y0, mut y1) = (f64::MAX, f64::MIN, f64::MAX, f64::MIN);
    for &(x, m, s) in &all {
        x0 = x0.min(x);
        x1 = x1.max(x);
        y0 = y0.min(m - s);
        y1 = y1.max(m + s);
    }
    if x1 <= x0 {
        x1 = x0 + 1.0;
    }
    let pad = ((y1 - y0) * 0.05).max(1e-6);
    let (y0, y1) = (y0 - pad, y1 + pad);

    let [w, h] = spec.size;
    let mut buf = vec![255u8; (w * h * 3) as usize];
    {
        let root = BitMapBackend::with_buffer(&mut buf, (w, h)).into_drawing_area();
        root.fill(&WHITE).map_err(|e| plot_err(path, e))?;
        let mut chart = ChartBuilder::on(&root)
            .caption(&spec.title, ("sans-serif", 22))
            .margin(12)
            .x_label_area_size(40)
            .y_label_area_size(60)
            .build_cartesian_2d(x0..x1, y0..y1)
            .map_err(|e| plot_err(path, e))?;
        chart
            .configure_mesh()
            .x_desc(spec.x_label.as_str())
            .y_desc(spec.y_label.as_str())
            .label_style(("sans-serif", 14))
            .draw()
            .map_err(|e| plot_err(path, e))?;
        for c in curves {
            let pts = points(c);
            let colour = RGBColor(c.colour[0], c.colour[1], c.colour[2]);
            if !c.std.is_empty() && pts.len() > 1 {
                let mut band: Vec<(f64, f64)> = pts.iter().map(|&(x, m, s)| (x, m + s)).collect();
                band.extend(pts.iter().rev().map(|&(x, m, s)| (x, m - s)));
                chart
                    .draw_series(std::iter::once(Polygon::new(
                        band,
                        colour.mix(0.2).filled(),
                    )))
                    .map_err(|e| plot_err(path, e))?;
            }
            chart
                .draw_series(LineSeries::new(
                    pts.iter().map(|&(x, m, _)| (x, m)),
                    colour.stroke_width(2),
                ))
                .map_err(|e| plot_err(path, e))?
                .label(c.label.as_str())
                .legend(move |(x, y)| {
                    PathElement::new([(x, y), (x + 20, y)], colour.stroke_width(3))
                });
        }
        chart
            .configure_series_labels()
            .background_style(WHITE.mix(0.85))
            .border_style(BLACK)
            .label_font(("sans-serif", 14))
            .draw()
            .map_err(|e| plot_err(path, e))?;
        root.present().map_err(|e| plot_err(path, e))?;
    }
    let img = image::RgbImage::from_raw(w, h, buf).expect("buffer of w*h*3 bytes");
    write_png_atomic(path, &img)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn draws_bands_in_the_curve_colours() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("radial.png");
        let x: Vec<f64> = (0..10).map(|i| i as f64 * 50.0).collect();
        let curves = [
            Curve {
                label: "standard".into(),
                colour: STANDARD_RED,
                x: x.clone(),
                mean: x.iter().map(|v| 1.0 + v / 500.0).collect(),
                std: vec![0.1; 10],
            },
            Curve {
                label: "calibrated".into(),
                colour: CALIBRATED_BLUE,
                x,
                mean: vec![1.0; 10],
                std: vec![0.05; 10],
            },
        ];
        let spec = PlotSpec {
            title: "RMSE vs radius".into(),
            x_label: "distance to principal point (px)".into(),
            y_label: "RMSE (m)".into(),
            ..Default::default()
        };
        line_band_plot(&path, &spec, &curves).unwrap();
        let img = image::open(&path).unwrap().to_rgb8();
        assert_eq!(img.dimensions(), (800, 500));
        let has = |c: [u8; 3]| img.pixels().any(|p| p.0 == c);
        assert!(has(STANDARD_RED) && has(CALIBRATED_BLUE));
        // Mismatched lengths are an error, not a panic.
        let mut bad = curves[0].clone();
        bad.std.pop();
        assert!(line_band_plot(&path, &spec, &[bad]).is_err());
    }
}
