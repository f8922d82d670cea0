//! Statistics of the report, in plain `f64`: means with Student-t confidence intervals over
//! seeds, and a seeded percentile bootstrap over test images.
//!
//! - Over seeds: `n` replicates `x_i` give the mean `m`, the sample standard deviation `s`
//!   (`ddof = 1`) and the 95% half-width `h = t(0.975, n - 1) s / sqrt(n)`; the interval is
//!   `[m - h, m + h]`. It needs `n >= 2` ([`MeanCi::half_width`] is `None` otherwise).
//! - The t quantile inverts the Student-t CDF, `F(t) = 1 - I_x(df/2, 1/2) / 2` for `t >= 0`
//!   with `x = df / (df + t^2)` and `I` the regularized incomplete beta function (its continued
//!   fraction, Numerical Recipes `betacf`), by bisection to [`QUANTILE_EPS`].
//! - Over test images ([`bootstrap`]): `resamples` multisets of `n` indices drawn uniformly with
//!   replacement from the project's SplitMix64 stream ([`crate::data::rng::Rng`]) seeded with
//!   `seed`; a statistic per resample; the
//!   interval is the `(1 - level) / 2` and `(1 + level) / 2` percentiles of the resampled values
//!   (linear interpolation between order statistics, numpy's default). Pairing is the caller's:
//!   the same indices select the same test images in both rows of a difference.

use crate::data::rng::Rng;

/// Bisection stops when the bracket is narrower than this (absolute, in t units).
pub const QUANTILE_EPS: f64 = 1e-12;
/// Continued-fraction iterations of the incomplete beta function (converges in < 100 for the
/// arguments of a t CDF with df <= 1e6).
const BETACF_MAX_ITER: usize = 300;
/// Relative accuracy at which the continued fraction stops.
const BETACF_EPS: f64 = 1e-15;

/// Arithmetic mean (NaN for no value).
pub fn mean(xs: &[f64]) -> f64 {
    if xs.is_empty() {
        return f64::NAN;
    }
    xs.iter().sum::<f64>() / xs.len() as f64
}

/// Sample standard deviation (`ddof = 1`; NaN for fewer than two values).
pub fn sample_sd(xs: &[f64]) -> f64 {
    if xs.len() < 2 {
        return f64::NAN;
    }
    let m = mean(xs);
    (xs.iter().map(|x| (x - m).powi(2)).sum::<f64>() / (xs.len() - 1) as f64).sqrt()
}

/// `ln Gamma(x)` for `x > 0` (Lanczos, g = 7, 9 terms; relative error ~1e-15).
pub fn ln_gamma(x: f64) -> f64 {
    const G: f64 = 7.0;
    const C: [f64; 9] = [
        0.999_999_999_999_809_9,
        676.520_368_121_885_1,
        -1_259.139_216_722_402_8,
        771.323_428_777_653_1,
        -176.615_029_162_140_6,
        12.507_343_278_686_905,
        -0.138_571_095_265_720_12,
        9.984_369_578_019_572e-6,
        1.505_632_735_149_311_6e-7,
    ];
    if x < 0.5 {
        // Reflection: Gamma(x) Gamma(1 - x) = pi / sin(pi x).
        return (std::f64::consts::PI / (std::f64::consts::PI * x).sin()).ln() - ln_gamma(1.0 - x);
    }
    let x = x - 1.0;
    let mut a = C[0];
    let t = x + G + 0.5;
    for (i, c) in C.iter().enumerate().skip(1) {
        a += c / (x + i as f64);
    }
    0.5 * (2.0 * std::f64::consts::PI).ln() + (x + 0.5) * t.ln() - t + a.ln()
}

/// Lentz's guard: a denominator this small is replaced by it (avoids dividing by zero).
const FPMIN: f64 = 1e-300;

/// One term `aa` of the modified Lentz method: updates `c` and `d` and returns the factor
/// `c * d` the continued fraction is multiplied by.
fn lentz_step(aa: f64, c: &mut f64, d: &mut f64) -> f64 {
    *d = 1.0 + aa * *d;
    if d.abs() < FPMIN {
        *d = FPMIN;
    }
    *c = 1.0 + aa / *c;
    if c.abs() < FPMIN {
        *c = FPMIN;
    }
    *d = 1.0 / *d;
    *d * *c
}

/// The continued fraction of the incomplete beta function (Lentz's method).
fn betacf(a: f64, b: f64, x: f64) -> f64 {
    let (qab, qap, qam) = (a + b, a + 1.0, a - 1.0);
    let mut c = 1.0;
    let mut d = 1.0 - qab * x / qap;
    if d.abs() < FPMIN {
        d = FPMIN;
    }
    d = 1.0 / d;
    let mut h = d;
    for m in 1..=BETACF_MAX_ITER {
        let m = m as f64;
        let m2 = 2.0 * m;
        // The even and the odd term of step m.
        let aa = m * (b - m) * x / ((qam + m2) * (a + m2));
        h *= lentz_step(aa, &mut c, &mut d);
        let aa = -(a + m) * (qab + m) * x / ((a + m2) * (qap + m2));
        let del = lentz_step(aa, &mut c, &mut d);
        h *= del;
        if (del - 1.0).abs() < BETACF_EPS {
            break;
        }
    }
    h
}

/// The regularized incomplete beta function `I_x(a, b)`, `0 <= x <= 1`.
pub fn inc_beta(a: f64, b: f64, x: f64) -> f64 {
    if x <= 0.0 {
        return 0.0;
    }
    if x >= 1.0 {
        return 1.0;
    }
    let ln_front = ln_gamma(a + b) - ln_gamma(a) - ln_gamma(b) + a * x.ln() + b * (1.0 - x).ln();
    let front = ln_front.exp();
    // The fraction converges fast for x < (a + 1) / (a + b + 2); use the symmetry otherwise.
    if x < (a + 1.0) / (a + b + 2.0) {
        front * betacf(a, b, x) / a
    } else {
        1.0 - front * betacf(b, a, 1.0 - x) / b
    }
}

/// The Student-t CDF with `df > 0` degrees of freedom.
pub fn student_t_cdf(t: f64, df: f64) -> f64 {
    let tail = 0.5 * inc_beta(df / 2.0, 0.5, df / (df + t * t));
    if t >= 0.0 {
        1.0 - tail
    } else {
        tail
    }
}

/// The `p` quantile of Student's t with `df > 0` degrees of freedom (`0 < p < 1`).
pub fn student_t_quantile(p: f64, df: f64) -> f64 {
    assert!(
        p > 0.0 && p < 1.0 && df > 0.0,
        "t quantile of p = {p}, df = {df}"
    );
    if p < 0.5 {
        return -student_t_quantile(1.0 - p, df);
    }
    let (mut lo, mut hi) = (0.0f64, 1.0f64);
    while student_t_cdf(hi, df) < p {
        hi *= 2.0;
    }
    while hi - lo > QUANTILE_EPS * hi.max(1.0) {
        let mid = 0.5 * (lo + hi);
        if student_t_cdf(mid, df) < p {
            lo = mid;
        } else {
            hi = mid;
        }
    }
    0.5 * (lo + hi)
}

/// A mean over replicates with its 95% Student-t interval.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct MeanCi {
    /// Replicates.
    pub n: usize,
    pub mean: f64,
    /// Sample standard deviation (NaN for `n < 2`).
    pub sd: f64,
    /// `t(0.975, n - 1) sd / sqrt(n)`; `None` for `n < 2`.
    pub half_width: Option<f64>,
}

impl MeanCi {
    /// The mean and 95% interval of `xs` (non-finite values are an error of the caller: they
    /// make the mean non-finite, so they show).
    pub fn of(xs: &[f64]) -> Self {
        let n = xs.len();
        let sd = sample_sd(xs);
        MeanCi {
            n,
            mean: mean(xs),
            sd,
            half_width: (n >= 2)
                .then(|| student_t_quantile(0.975, (n - 1) as f64) * sd / (n as f64).sqrt()),
        }
    }

    /// `[mean - h, mean + h]`, if there is an interval.
    pub fn interval(&self) -> Option<[f64; 2]> {
        self.half_width.map(|h| [self.mean - h, self.mean + h])
    }
}

/// The `q` quantile (`0..=1`) of sorted finite values, linear between order statistics.
pub fn percentile(sorted: &[f64], q: f64) -> f64 {
    if sorted.is_empty() {
        return f64::NAN;
    }
    let pos = q * (sorted.len() - 1) as f64;
    let (i, f) = (pos.floor() as usize, pos - pos.floor());
    if i + 1 >= sorted.len() {
        sorted[sorted.len() - 1]
    } else {
        sorted[i] * (1.0 - f) + sorted[i + 1] * f
    }
}

/// Percentile bootstrap intervals at `level` of `k` statistics of `n` items: `stat` gets the
/// indices of one resample (length `n`, with repeats) and returns the `k` values. Resamples
/// where a value is not finite are left out of that value's interval (`None` if fewer than
/// half remain).
pub fn bootstrap(
    n: usize,
    k: usize,
    resamples: usize,
    seed: u64,
    level: f64,
    mut stat: impl FnMut(&[usize]) -> Vec<f64>,
) -> Vec<Option<[f64; 2]>> {
    let mut rng = Rng::new(seed);
    let mut values = vec![Vec::with_capacity(resamples); k];
    let mut idx = vec![0usize; n];
    if n == 0 {
        return vec![None; k];
    }
    for _ in 0..resamples {
        for i in idx.iter_mut() {
            *i = rng.below(n as u64) as usize;
        }
        for (j, v) in stat(&idx).into_iter().enumerate().take(k) {
            if v.is_finite() {
                values[j].push(v);
            }
        }
    }
    values
        .into_iter()
        .map(|mut v| {
            if v.len() * 2 < resamples.max(1) {
                return None;
            }
            v.sort_by(f64::total_cmp);
            Some([
                percentile(&v, (1.0 - level) / 2.0),
                percentile(&v, (1.0 + level) / 2.0),
            ])
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The published t-table values below have 6-7 significant digits.
    const TABLE_TOL: f64 = 5e-6;

    #[test]
    fn t_quantiles_match_the_tables() {
        for (df, want) in [
            (1.0, 12.706_204_736),
            (2.0, 4.302_652_73),
            (4.0, 2.776_445_105),
            (30.0, 2.042_272_456),
        ] {
            let got = student_t_quantile(0.975, df);
            assert!(
                (got - want).abs() < TABLE_TOL * want,
                "df {df}: {got} vs {want}"
            );
        }
        // Closed forms: df 1 is Cauchy, tan(pi (p - 1/2)); df 2 is (2p - 1) / sqrt(2 p (1 - p)).
        for p in [0.6, 0.9, 0.995] {
            let c = (std::f64::consts::PI * (p - 0.5)).tan();
            assert!((student_t_quantile(p, 1.0) - c).abs() < 1e-9 * c.max(1.0));
            let t2 = (2.0 * p - 1.0) / (2.0 * p * (1.0 - p)).sqrt();
            assert!((student_t_quantile(p, 2.0) - t2).abs() < 1e-9);
        }
        assert!((student_t_quantile(0.025, 4.0) + 2.776_445_105).abs() < 1e-5);
        // Large df approaches the normal quantile 1.959964.
        assert!((student_t_quantile(0.975, 1e6) - 1.959_964).abs() < 1e-5);
    }

    #[test]
    fn ln_gamma_and_cdf_by_hand() {
        // Gamma(5) = 24, Gamma(1/2) = sqrt(pi).
        assert!((ln_gamma(5.0) - 24f64.ln()).abs() < 1e-13);
        assert!((ln_gamma(0.5) - std::f64::consts::PI.sqrt().ln()).abs() < 1e-13);
        assert_eq!(student_t_cdf(0.0, 3.0), 0.5);
        // df 1: F(1) = 3/4.
        assert!((student_t_cdf(1.0, 1.0) - 0.75).abs() < 1e-13);
    }

    #[test]
    fn mean_ci_by_hand() {
        // 1, 2, 3: mean 2, sd 1, h = t(0.975, 2) / sqrt 3.
        let c = MeanCi::of(&[1.0, 2.0, 3.0]);
        assert_eq!((c.n, c.mean, c.sd), (3, 2.0, 1.0));
        let h = 4.302_652_73 / 3f64.sqrt();
        assert!((c.half_width.unwrap() - h).abs() < 1e-6);
        assert_eq!(c.interval().unwrap()[0], 2.0 - c.half_width.unwrap());
        // One replicate: a mean, no interval.
        let c = MeanCi::of(&[0.7]);
        assert_eq!((c.n, c.mean, c.half_width), (1, 0.7, None));
        assert!(c.sd.is_nan());
    }

    #[test]
    fn bootstrap_is_seeded_and_brackets_the_mean() {
        let xs: Vec<f64> = (0..50).map(|i| (i % 7) as f64).collect();
        let stat = |idx: &[usize]| vec![idx.iter().map(|&i| xs[i]).sum::<f64>() / idx.len() as f64];
        let a = bootstrap(xs.len(), 1, 2000, 7, 0.95, stat);
        let b = bootstrap(xs.len(), 1, 2000, 7, 0.95, stat);
        assert_eq!(a, b);
        let [lo, hi] = a[0].unwrap();
        let m = mean(&xs);
        assert!(lo < m && m < hi, "{lo} {m} {hi}");
        // Close to the normal approximation m +- 1.96 sd / sqrt(n) (within 20%: resampling).
        let w = 1.96 * sample_sd(&xs) / (xs.len() as f64).sqrt();
        assert!(
            ((hi - lo) / 2.0 - w).abs() < 0.2 * w,
            "{} vs {w}",
            (hi - lo) / 2.0
        );
        // A constant statistic has a zero-width interval; an always-NaN one none.
        let c = bootstrap(10, 2, 100, 1, 0.95, |_| vec![3.0, f64::NAN]);
        assert_eq!(c, vec![Some([3.0, 3.0]), None]);
        assert_eq!(percentile(&[1.0, 2.0, 3.0, 4.0], 0.5), 2.5);
    }
}
