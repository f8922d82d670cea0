//! Small helpers the training loop, evaluation and the reports share: number formatting for CSV
//! files and progress bars on stderr.

/// A float for CSV: empty for NaN (spreadsheets and pandas read it as missing).
pub fn fmt_f64(v: f64) -> String {
    if v.is_nan() {
        String::new()
    } else {
        format!("{v}")
    }
}

/// A progress bar on stderr with position, rate and ETA (hidden when `enabled` is false or
/// stderr is not a terminal).
pub fn progress_bar(len: u64, label: &str, enabled: bool) -> indicatif::ProgressBar {
    if !enabled {
        return indicatif::ProgressBar::hidden();
    }
    let bar = indicatif::ProgressBar::new(len);
    bar.set_style(
        indicatif::ProgressStyle::with_template(
            "{prefix:>6} [{bar:30}] {pos}/{len} {msg} ({elapsed} < {eta})",
        )
        .expect("valid template")
        .progress_chars("=> "),
    );
    bar.set_prefix(label.to_string());
    bar
}
