//! The order of training windows: a fresh permutation per epoch, a function of (seed, epoch) only, so that
//! the data position of any step can be recomputed on resume, and a disjoint slice per rank.

use rand::seq::SliceRandom;
use rand::{SeedableRng, rngs::StdRng};

/// Which windows each step uses.
#[derive(Debug, Clone)]
pub struct Sampler {
    n: usize,
    seed: u64,
    cached: Option<(u64, Vec<usize>)>,
}

impl Sampler {
    /// Over `n` windows.
    pub fn new(n: usize, seed: u64) -> Self {
        Self {
            n,
            seed,
            cached: None,
        }
    }

    /// Window of global sample number `g` (samples run through epochs back to back).
    pub fn window(&mut self, g: u64) -> usize {
        let n = self.n.max(1) as u64;
        let (epoch, i) = (g / n, (g % n) as usize);
        if self.cached.as_ref().is_none_or(|(e, _)| *e != epoch) {
            let mut perm: Vec<usize> = (0..self.n).collect();
            perm.shuffle(&mut StdRng::seed_from_u64(
                self.seed ^ epoch.wrapping_mul(0x9e37_79b9_7f4a_7c15),
            ));
            self.cached = Some((epoch, perm));
        }
        self.cached.as_ref().map_or(i, |(_, p)| p[i])
    }

    /// Windows of micro-batch `micro` of `step` for `rank` of `world`: each step takes
    /// `batch × accum × world` consecutive samples, rank-major within each micro-batch.
    pub fn batch(
        &mut self,
        step: u64,
        micro: usize,
        accum: usize,
        batch: usize,
        rank: usize,
        world: usize,
    ) -> Vec<usize> {
        let per_step = (batch * accum * world) as u64;
        let start = step * per_step + ((micro * world + rank) * batch) as u64;
        (0..batch as u64).map(|k| self.window(start + k)).collect()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn epochs_are_permutations_and_ranks_are_disjoint() {
        let mut s = Sampler::new(10, 3);
        let first: Vec<usize> = (0..10).map(|g| s.window(g)).collect();
        let mut sorted = first.clone();
        sorted.sort();
        assert_eq!(sorted, (0..10).collect::<Vec<_>>());
        let second: Vec<usize> = (10..20).map(|g| s.window(g)).collect();
        assert_ne!(first, second, "a new order each epoch");
        assert_eq!(
            Sampler::new(10, 3).window(13),
            second[3],
            "a function of (seed, sample) only"
        );
        // Two ranks, accumulation 2, batch 2: one step takes 8 samples, each exactly once.
        let mut all = Vec::new();
        for micro in 0..2 {
            for rank in 0..2 {
                all.extend(Sampler::new(100, 1).batch(5, micro, 2, 2, rank, 2));
            }
        }
        let want: Vec<usize> = (40..48).map(|g| Sampler::new(100, 1).window(g)).collect();
        all.sort();
        let mut want_sorted = want;
        want_sorted.sort();
        assert_eq!(all, want_sorted);
    }
}
