//! Maximum mean discrepancy with one Gaussian kernel, as the authors' `MMD_loss` (kernel_mul 1,
//! kernel_num 1): k(a, b) = exp(−‖a − b‖² / bw), bw = Σ over all pairs of the pooled samples of ‖a − b‖²
//! divided by (n + m)² − (n + m) (the mean squared distance between distinct samples), and the biased
//! statistic mean k(X, X) + mean k(Y, Y) − 2 mean k(X, Y).

use umgen_scene::Agent;

/// Attribute groups compared between generated and real agents.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Group {
    /// x, y (m).
    Position,
    /// Heading as (cos, sin), so that −π and π are neighbours.
    Heading,
    /// Length, width, height (m).
    Size,
    /// vx, vy (m/s).
    Velocity,
}

impl Group {
    /// All groups, in report order.
    pub const ALL: [Group; 4] = [Group::Position, Group::Heading, Group::Size, Group::Velocity];

    /// Name in reports.
    pub fn name(self) -> &'static str {
        match self {
            Group::Position => "position",
            Group::Heading => "heading",
            Group::Size => "size",
            Group::Velocity => "velocity",
        }
    }

    /// The group's features of an agent.
    pub fn features(self, a: &Agent) -> Vec<f64> {
        match self {
            Group::Position => vec![a.x, a.y],
            Group::Heading => vec![a.heading.cos(), a.heading.sin()],
            Group::Size => vec![a.length, a.width, a.height],
            Group::Velocity => vec![a.vx, a.vy],
        }
    }
}

fn sq(a: &[f64], b: &[f64]) -> f64 {
    a.iter().zip(b).map(|(x, y)| (x - y) * (x - y)).sum()
}

/// MMD² between samples `x` and `y` (each a list of feature vectors of one length); `None` when either is
/// empty. Identical sets give 0.
pub fn mmd(x: &[Vec<f64>], y: &[Vec<f64>]) -> Option<f64> {
    if x.is_empty() || y.is_empty() {
        return None;
    }
    let all: Vec<&Vec<f64>> = x.iter().chain(y).collect();
    let n = all.len();
    let total: f64 = all.iter().flat_map(|a| all.iter().map(move |b| sq(a, b))).sum();
    let pairs = (n * n - n) as f64;
    let bw = if pairs > 0.0 && total > 0.0 {
        total / pairs
    } else {
        1.0
    };
    let mean_k = |p: &[Vec<f64>], q: &[Vec<f64>]| {
        p.iter()
            .flat_map(|a| q.iter().map(move |b| (-sq(a, b) / bw).exp()))
            .sum::<f64>()
            / (p.len() * q.len()) as f64
    };
    Some(mean_k(x, x) + mean_k(y, y) - 2.0 * mean_k(x, y))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn identical_sets_are_zero_and_a_hand_computed_pair() {
        let x = vec![vec![0.0, 1.0], vec![2.0, -1.0], vec![0.5, 0.5]];
        assert_eq!(mmd(&x, &x).map(|v| v.abs() < 1e-12), Some(true));
        // One point each, 2 apart: bw = (4 + 4) / 2 = 4; MMD² = 1 + 1 − 2·e^(−1).
        let got = mmd(&[vec![0.0]], &[vec![2.0]]).unwrap_or(f64::NAN);
        assert!((got - (2.0 - 2.0 * (-1.0f64).exp())).abs() < 1e-12, "{got}");
        // Farther apart sets differ more (relative to a fixed reference cloud).
        let near: Vec<Vec<f64>> = x.iter().map(|v| vec![v[0] + 0.1, v[1]]).collect();
        let far: Vec<Vec<f64>> = x.iter().map(|v| vec![v[0] + 3.0, v[1]]).collect();
        assert!(mmd(&x, &near).unwrap_or(0.0) < mmd(&x, &far).unwrap_or(0.0));
        assert_eq!(mmd(&[], &x), None);
    }
}
