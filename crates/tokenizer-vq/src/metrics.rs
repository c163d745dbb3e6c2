//! Reconstruction quality: IoU per binary channel, PSNR of colour images, codebook statistics.

/// Running intersection and union counts per channel of binary rasters.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct IouCounter {
    inter: Vec<u64>,
    union: Vec<u64>,
    positives: Vec<u64>,
}

impl IouCounter {
    /// Adds a batch of `[B, C, H·W]` rasters (`plane` = H·W values per channel); a value above 0.5 is
    /// positive.
    pub fn add(&mut self, channels: usize, plane: usize, pred: &[f32], target: &[f32]) {
        if self.inter.len() != channels {
            *self = Self {
                inter: vec![0; channels],
                union: vec![0; channels],
                positives: vec![0; channels],
            };
        }
        for (i, (p, t)) in pred.iter().zip(target).enumerate() {
            let c = (i / plane.max(1)) % channels;
            let (p, t) = (*p > 0.5, *t > 0.5);
            self.inter[c] += u64::from(p && t);
            self.union[c] += u64::from(p || t);
            self.positives[c] += u64::from(t);
        }
    }

    /// IoU per channel; `None` for a channel that is empty in both prediction and target.
    pub fn iou(&self) -> Vec<Option<f64>> {
        self.inter
            .iter()
            .zip(&self.union)
            .map(|(&i, &u)| (u > 0).then(|| i as f64 / u as f64))
            .collect()
    }

    /// Positive target pixels per channel (how present a layer is).
    pub fn positives(&self) -> &[u64] {
        &self.positives
    }
}

/// Running squared error of colour images in [-1, 1].
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct PsnrCounter {
    sq: f64,
    n: u64,
}

impl PsnrCounter {
    /// Adds a batch.
    pub fn add(&mut self, pred: &[f32], target: &[f32]) {
        for (p, t) in pred.iter().zip(target) {
            // To [0, 1], the range PSNR is stated in.
            let d = f64::from(p.clamp(-1.0, 1.0) - t) / 2.0;
            self.sq += d * d;
            self.n += 1;
        }
    }

    /// Peak signal-to-noise ratio in dB over everything added (infinite when exact).
    pub fn psnr(&self) -> f64 {
        let mse = self.sq / self.n.max(1) as f64;
        -10.0 * mse.log10()
    }
}

/// Codebook statistics of a set of code ids: the fraction of entries used, and the perplexity
/// `exp(entropy)` of their frequencies (the effective number of codes in use).
pub fn code_stats(ids: &[u32], codebook_size: usize) -> (f64, f64) {
    let mut counts = vec![0f64; codebook_size];
    for &i in ids {
        if let Some(c) = counts.get_mut(i as usize) {
            *c += 1.0;
        }
    }
    count_stats(&counts)
}

/// [`code_stats`] from a histogram: uses per code (one entry per codebook entry).
pub fn count_stats(counts: &[f64]) -> (f64, f64) {
    let n = counts.iter().sum::<f64>().max(1.0);
    let used = counts.iter().filter(|&&c| c > 0.0).count() as f64 / counts.len().max(1) as f64;
    let entropy: f64 = counts
        .iter()
        .filter(|&&c| c > 0.0)
        .map(|&c| -(c / n) * (c / n).ln())
        .sum();
    (used, entropy.exp())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn iou_psnr_and_perplexity_on_hand_computed_cases() {
        let mut c = IouCounter::default();
        // One image, two channels of 4 pixels.
        c.add(
            2,
            4,
            &[1.0, 1.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0],
            &[1.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 0.0],
        );
        assert_eq!(c.iou(), vec![Some(1.0 / 3.0), None]);
        assert_eq!(c.positives(), &[2, 0]);
        let mut p = PsnrCounter::default();
        // Errors of 0.2 in [-1, 1] are 0.1 in [0, 1]: MSE 0.01, PSNR 20 dB.
        p.add(&[0.2, -0.2], &[0.0, 0.0]);
        assert!((p.psnr() - 20.0).abs() < 1e-5, "{}", p.psnr());
        let (used, ppl) = code_stats(&[0, 1, 2, 3, 0, 1, 2, 3], 8);
        assert!((used - 0.5).abs() < 1e-12 && (ppl - 4.0).abs() < 1e-9);
    }
}
