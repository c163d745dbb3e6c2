//! How far a rate measured from a count of events (agents entering, leaving, collisions begun) can be
//! trusted: a count `k` taken as Poisson-distributed, and its 95 % interval. A second of a 64-scene
//! rollout holds about 28 entries, whose count alone moves by ±19 % from rollout to rollout; a rate is
//! only off its target where the interval says so.

/// The 97.5th percentile of the standard normal distribution.
const Z_975: f64 = 1.959_963_984_540_054;

/// Counts up to this are given their exact interval; above it Byar's approximation, within 0.1 % of it
/// there, takes over (the exact one sums the distribution, whose terms underflow for large means).
const EXACT_UP_TO: usize = 100;

/// The 95 % interval of the mean of a Poisson variable observed as `k`: the exact (Garwood) interval, the
/// means at which P(X ≥ k) and P(X ≤ k) are 2.5 %, up to [`EXACT_UP_TO`]; Byar's approximation to it
/// beyond.
pub fn poisson_95(k: usize) -> [f64; 2] {
    if k > EXACT_UP_TO {
        return byar_95(k);
    }
    // P(X ≤ k) for mean `mu`, falling in `mu`.
    let cdf = |k: usize, mu: f64| {
        let (mut term, mut sum) = ((-mu).exp(), 0.0);
        for i in 0..=k {
            if i > 0 {
                term *= mu / i as f64;
            }
            sum += term;
        }
        sum
    };
    // The mean in [0, 200] at which the falling `f` crosses `target`.
    let solve = |f: &dyn Fn(f64) -> f64, target: f64| {
        let (mut a, mut b) = (0.0, 200.0);
        for _ in 0..100 {
            let m = 0.5 * (a + b);
            if f(m) > target { a = m } else { b = m }
        }
        0.5 * (a + b)
    };
    let hi = solve(&|mu| cdf(k, mu), 0.025);
    // P(X ≥ k) = 1 − P(X ≤ k − 1) reaches 2.5 % where P(X ≤ k − 1) falls to 97.5 %.
    let lo = if k == 0 {
        0.0
    } else {
        solve(&|mu| cdf(k - 1, mu), 0.975)
    };
    [lo, hi]
}

/// Byar's approximation to the exact 95 % interval of a Poisson count `k` ≥ 1.
fn byar_95(k: usize) -> [f64; 2] {
    let cube = |x: f64| x * x * x;
    let k = k as f64;
    let lo = k * cube(1.0 - 1.0 / (9.0 * k) - Z_975 / (3.0 * k.sqrt()));
    let k1 = k + 1.0;
    let hi = k1 * cube(1.0 - 1.0 / (9.0 * k1) + Z_975 / (3.0 * k1.sqrt()));
    [lo, hi]
}

/// The 95 % interval of a rate per second from `k` events over `seconds` (`None` without time).
pub fn rate_95(k: usize, seconds: f64) -> Option<[f64; 2]> {
    (seconds > 0.0).then(|| poisson_95(k).map(|x| x / seconds))
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The exact 95 % Poisson intervals (the means at which P(X ≥ k) and P(X ≤ k) are 0.025), found by
    /// bisection on the Poisson distribution function; the same as χ²(0.025, 2k) / 2 and
    /// χ²(0.975, 2k + 2) / 2 in published tables.
    const EXACT: [(usize, f64, f64); 6] = [
        (0, 0.0, 3.689),
        (1, 0.0253, 5.572),
        (5, 1.623, 11.668),
        (10, 4.795, 18.390),
        (28, 18.606, 40.467),
        (100, 81.364, 121.627),
    ];

    #[test]
    fn intervals_match_the_exact_ones() {
        for (k, lo, hi) in EXACT {
            let [a, b] = poisson_95(k);
            assert!((b - hi).abs() <= 1e-3 * hi, "k = {k}: upper {b} against {hi}");
            assert!(
                (a - lo).abs() <= 1e-3 * lo.max(0.01),
                "k = {k}: lower {a} against {lo}"
            );
            assert!(
                a <= k as f64 && k as f64 <= b,
                "k = {k}: [{a}, {b}] holds the count"
            );
        }
        // Where the exact computation hands over to Byar's, the two agree within 0.1 %.
        let ([a, b], [c, d]) = (poisson_95(EXACT_UP_TO), byar_95(EXACT_UP_TO));
        assert!(
            (a - c).abs() < 1e-3 * a && (b - d).abs() < 1e-3 * b,
            "[{a}, {b}] against [{c}, {d}]"
        );
    }

    #[test]
    fn the_interval_narrows_relative_to_the_count_and_scales_with_time() {
        let width = |k: usize| {
            let [a, b] = poisson_95(k);
            (b - a) / k as f64
        };
        assert!(width(10) > width(100) && width(100) > width(1000));
        // About ±2/√k for large counts.
        assert!((width(10_000) - 2.0 * Z_975 / 100.0).abs() < 1e-3);
        assert_eq!(rate_95(28, 0.0), None);
        let [a, b] = rate_95(28, 64.0).unwrap_or_default();
        let [ea, eb] = poisson_95(28);
        assert!((a - ea / 64.0).abs() < 1e-12 && (b - eb / 64.0).abs() < 1e-12);
    }
}
