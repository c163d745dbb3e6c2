//! Reconstruction quality: IoU per binary channel, PSNR of colour images, codebook statistics.

/// Running intersection and union counts per channel of binary rasters, and the same within one pixel.
///
/// Markings one pixel wide (stop lines, lane dividers at 0.5 m per pixel) lose all their overlap when a
/// reconstruction is one pixel off, so exact IoU alone cannot tell a shifted line from a missing one; the
/// within-one-pixel counts (a positive matches if the other raster has a positive in its 3×3
/// neighbourhood, as the boundary F-measure of contour detection does) can.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct IouCounter {
    inter: Vec<u64>,
    union: Vec<u64>,
    positives: Vec<u64>,
    predicted: Vec<u64>,
    /// Predicted positives with a target positive within one pixel.
    pred_near: Vec<u64>,
    /// Target positives with a predicted positive within one pixel.
    target_near: Vec<u64>,
}

/// Precision, recall and F1 of one channel's positives, each within one pixel.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct NearScores {
    /// Fraction of predicted positives with a target positive within one pixel.
    pub precision: f64,
    /// Fraction of target positives with a predicted positive within one pixel.
    pub recall: f64,
    /// Harmonic mean of the two.
    pub f1: f64,
}

impl IouCounter {
    /// Adds a batch of `[B, C, H, W]` rasters (`size` = [H, W]); a value above 0.5 is positive.
    pub fn add(&mut self, channels: usize, size: [usize; 2], pred: &[f32], target: &[f32]) {
        if self.inter.len() != channels {
            *self = Self {
                inter: vec![0; channels],
                union: vec![0; channels],
                positives: vec![0; channels],
                predicted: vec![0; channels],
                pred_near: vec![0; channels],
                target_near: vec![0; channels],
            };
        }
        let [h, w] = size;
        let plane = (h * w).max(1);
        for (k, (p, t)) in pred.chunks(plane).zip(target.chunks(plane)).enumerate() {
            let c = k % channels.max(1);
            let p: Vec<bool> = p.iter().map(|v| *v > 0.5).collect();
            let t: Vec<bool> = t.iter().map(|v| *v > 0.5).collect();
            for (i, (&a, &b)) in p.iter().zip(&t).enumerate() {
                self.inter[c] += u64::from(a && b);
                self.union[c] += u64::from(a || b);
                self.positives[c] += u64::from(b);
                self.predicted[c] += u64::from(a);
                self.pred_near[c] += u64::from(a && near(&t, [h, w], i));
                self.target_near[c] += u64::from(b && near(&p, [h, w], i));
            }
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

    /// Precision, recall and F1 within one pixel per channel; `None` for a channel that is empty in both.
    pub fn near(&self) -> Vec<Option<NearScores>> {
        (0..self.inter.len())
            .map(|c| {
                let (np, nt) = (self.predicted[c], self.positives[c]);
                (np + nt > 0).then(|| {
                    let precision = self.pred_near[c] as f64 / np.max(1) as f64;
                    let recall = self.target_near[c] as f64 / nt.max(1) as f64;
                    let f1 = if precision + recall > 0.0 {
                        2.0 * precision * recall / (precision + recall)
                    } else {
                        0.0
                    };
                    NearScores {
                        precision,
                        recall,
                        f1,
                    }
                })
            })
            .collect()
    }

    /// Positive target pixels per channel (how present a layer is).
    pub fn positives(&self) -> &[u64] {
        &self.positives
    }
}

/// Whether `mask` has a positive in the 3×3 neighbourhood of pixel `i` of an `[h, w]` plane.
fn near(mask: &[bool], [h, w]: [usize; 2], i: usize) -> bool {
    let (r, c) = (i / w.max(1), i % w.max(1));
    (r.saturating_sub(1)..(r + 2).min(h))
        .any(|rr| (c.saturating_sub(1)..(c + 2).min(w)).any(|cc| mask[rr * w + cc]))
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
            [2, 2],
            &[1.0, 1.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0],
            &[1.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 0.0],
        );
        assert_eq!(c.iou(), vec![Some(1.0 / 3.0), None]);
        assert_eq!(c.positives(), &[2, 0]);
        // In a 2×2 plane every pixel neighbours every other: all within one pixel.
        let near = c.near()[0].unwrap();
        assert_eq!((near.precision, near.recall, near.f1), (1.0, 1.0, 1.0));
        assert_eq!(c.near()[1], None);
        let mut p = PsnrCounter::default();
        // Errors of 0.2 in [-1, 1] are 0.1 in [0, 1]: MSE 0.01, PSNR 20 dB.
        p.add(&[0.2, -0.2], &[0.0, 0.0]);
        assert!((p.psnr() - 20.0).abs() < 1e-5, "{}", p.psnr());
        let (used, ppl) = code_stats(&[0, 1, 2, 3, 0, 1, 2, 3], 8);
        assert!((used - 0.5).abs() < 1e-12 && (ppl - 4.0).abs() < 1e-9);
    }

    #[test]
    fn a_line_one_pixel_off_has_no_iou_but_matches_within_a_pixel() {
        // A vertical line in column 2 of a 5×5 plane, reconstructed in column 3, plus a stray pixel two
        // columns from it; a second image has the line but no reconstruction.
        let line = |col: usize| -> Vec<f32> { (0..25).map(|i| f32::from(u8::from(i % 5 == col))).collect() };
        let mut pred = line(3);
        pred[0] = 1.0;
        let mut c = IouCounter::default();
        c.add(
            1,
            [5, 5],
            &[pred, vec![0.0; 25]].concat(),
            &[line(2), line(2)].concat(),
        );
        assert_eq!(c.iou(), vec![Some(0.0)]);
        let n = c.near()[0].unwrap();
        // Precision: 5 of 6 predicted pixels lie next to the line (the stray one is two columns away).
        // Recall: 5 of 10 line pixels have a prediction next to them.
        assert!((n.precision - 5.0 / 6.0).abs() < 1e-12, "{n:?}");
        assert!((n.recall - 0.5).abs() < 1e-12, "{n:?}");
        let f1 = 2.0 * (5.0 / 6.0) * 0.5 / (5.0 / 6.0 + 0.5);
        assert!((n.f1 - f1).abs() < 1e-12, "{n:?}");
    }
}
