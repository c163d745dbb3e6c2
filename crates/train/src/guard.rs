//! Steps whose loss or gradient norm is not finite: skipped on the device as they happen (the optimizer's
//! guarded step), counted there, and reported and acted on (`train.nonfinite`) when the host reads the
//! losses, so that guarding costs no wait for the device.

use crate::config::NonFinite;
use crate::error::{Result, TrainError};
use burn::tensor::Tensor;
use burn::tensor::backend::Backend;
use umgen_optim::GradientPeak;

/// The device-side count of skipped steps between two reads.
pub(crate) struct Guard<B: Backend> {
    policy: NonFinite,
    limit: u64,
    /// Whether the loss guards the step: with one rank. With several, each rank's loss is its own, and a
    /// step applied on some ranks only would split the model; the gradient norm, the same on every rank
    /// after the all-reduce, guards it alone (a non-finite loss makes non-finite gradients).
    loss_guards: bool,
    /// `[1]`: steps observed since the last read.
    since: Tensor<B, 1>,
    /// `[1]`: steps skipped since the last read.
    skipped: Tensor<B, 1>,
    /// `[1]`: steps skipped in a row, up to the latest.
    streak: Tensor<B, 1>,
    /// The first skipped step since the last read: its offset from the read, its losses, gradient norm
    /// and sums of squares by part.
    first: Option<Tensor<B, 1>>,
    /// Steps done at the last read.
    read_at: u64,
}

/// A skipped step, as read back.
#[derive(Debug, Clone)]
pub(crate) struct SkipReport {
    /// Steps skipped since the previous read.
    pub skipped: u64,
    /// Steps skipped in a row, up to the read.
    pub streak: u64,
    /// The first skipped step since the previous read (1-based, as steps are counted).
    pub step: u64,
    /// Its loss terms, gradient norm and largest gradient, in words.
    pub what: String,
}

impl<B: Backend> Guard<B> {
    /// A guard for a run at `step` with `world` ranks.
    pub(crate) fn new(policy: NonFinite, limit: u64, world: usize, step: u64, device: &B::Device) -> Self {
        let zero = || Tensor::zeros([1], device);
        Self {
            policy,
            limit,
            loss_guards: world == 1,
            since: zero(),
            skipped: zero(),
            streak: zero(),
            first: None,
            read_at: step,
        }
    }

    /// What must be finite for this step to apply: the loss (`[1]`) with one rank, and under
    /// `nonfinite = "stop"` nothing once a step has been skipped since the last read (the run stops there
    /// with the weights from before that step).
    pub(crate) fn values(&self, loss: Tensor<B, 1>) -> Option<Tensor<B, 1>> {
        let latch = (self.policy == NonFinite::Stop).then(|| {
            let skipped = self.skipped.clone().greater_elem(0.0);
            self.skipped.zeros_like().mask_fill(skipped, f32::NAN)
        });
        match (self.loss_guards, latch) {
            (true, Some(l)) => Some(Tensor::cat(vec![loss, l], 0)),
            (true, None) => Some(loss),
            (false, l) => l,
        }
    }

    /// Counts a step: `skipped` (`[1]`, 0 or 1) as the optimizer reported it, with the step's `losses`
    /// (total first), gradient `norm` and sums of squares by `parts`.
    pub(crate) fn observe(
        &mut self,
        skipped: Tensor<B, 1>,
        losses: Tensor<B, 1>,
        norm: Tensor<B, 1>,
        parts: Tensor<B, 1>,
    ) {
        let record = Tensor::cat(vec![self.since.clone(), losses, norm, parts], 0);
        let take = skipped
            .clone()
            .greater_elem(0.5)
            .bool_and(self.skipped.clone().equal_elem(0.0));
        let base = match self.first.take() {
            Some(f) if f.dims() == record.dims() => f,
            _ => record.zeros_like(),
        };
        self.first = Some(base.mask_where(take.expand(record.shape()), record));
        self.skipped = self.skipped.clone() + skipped.clone();
        self.streak = self.streak.clone().add_scalar(1.0) * skipped;
        self.since = self.since.clone().add_scalar(1.0);
    }

    /// What a read appends to the losses it fetches: skipped steps, the streak and the first skipped
    /// step's record.
    pub(crate) fn pending(&self) -> Tensor<B, 1> {
        let mut v = vec![self.skipped.clone(), self.streak.clone()];
        v.extend(self.first.clone());
        Tensor::cat(v, 0)
    }

    /// Steps skipped in a row up to now (waits for the device).
    pub(crate) fn streak_now(&self) -> f64 {
        self.streak
            .clone()
            .into_data()
            .iter::<f64>()
            .next()
            .unwrap_or(0.0)
    }

    /// Takes the values [`Guard::pending`] appended, as read at step `step`, with the names of the loss
    /// terms and a namer of the largest gradient; resets the counts. `Ok(None)` when no step was skipped,
    /// an error when the run must stop.
    pub(crate) fn settle(
        &mut self,
        values: &[f64],
        step: u64,
        names: &[String],
        largest: impl Fn(&[f32]) -> Option<GradientPeak>,
    ) -> Result<Option<SkipReport>> {
        let read_at = std::mem::replace(&mut self.read_at, step);
        self.skipped = self.skipped.zeros_like();
        self.since = self.since.zeros_like();
        let (skipped, streak) = match values {
            [a, b, ..] => (*a as u64, *b as u64),
            _ => return Ok(None),
        };
        if skipped == 0 {
            return Ok(None);
        }
        let record = &values[2..];
        let l = names.len();
        let offset = record.first().copied().unwrap_or(0.0) as u64;
        let losses = record.get(1..1 + l).unwrap_or_default();
        let norm = record.get(1 + l).copied().unwrap_or(f64::NAN);
        let parts: Vec<f32> = record
            .get(2 + l..)
            .unwrap_or_default()
            .iter()
            .map(|&x| x as f32)
            .collect();
        let terms: Vec<String> = names
            .iter()
            .zip(losses)
            .map(|(k, v)| format!("{k} {v:.4}"))
            .collect();
        let mut what = format!("{}; gradient norm {norm:.4}", terms.join(", "));
        match largest(&parts) {
            Some(p) if p.non_finite > 0 => what.push_str(&format!(
                "; the gradients of {} of {} parameters are not finite, the first `{}`",
                p.non_finite, p.params, p.name
            )),
            Some(p) => what.push_str(&format!("; largest gradient `{}` (norm {:.4})", p.name, p.norm)),
            None => {}
        }
        let report = SkipReport {
            skipped,
            streak,
            step: read_at + offset + 1,
            what,
        };
        if self.policy == NonFinite::Stop {
            return Err(TrainError::NonFinite {
                step: report.step,
                message: format!("{} (train.nonfinite = \"stop\")", report.what),
            });
        }
        if streak >= self.limit {
            // The streak may have begun before the previous read; its first step is the one to name.
            let start = (step + 1).saturating_sub(streak);
            return Err(TrainError::NonFinite {
                step: start,
                message: format!(
                    "{streak} steps in a row skipped (steps {start} to {step}), train.max_skipped_steps = {}; at step {}: {}",
                    self.limit, report.step, report.what
                ),
            });
        }
        Ok(Some(report))
    }
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]
    use super::*;

    type B = burn::backend::Flex;

    fn t(v: &[f32]) -> Tensor<B, 1> {
        Tensor::from_floats(v, &Default::default())
    }

    /// Feeds steps (skipped or not, with their total loss) to `g` and reads as the trainer does.
    fn run(g: &mut Guard<B>, steps: &[(bool, f32)], read_at: u64) -> Result<Option<SkipReport>> {
        for &(skipped, loss) in steps {
            let s = t(&[if skipped { 1.0 } else { 0.0 }]);
            g.observe(s, t(&[loss, loss / 2.0]), t(&[loss]), t(&[1.0, loss, 4.0]));
        }
        let values: Vec<f64> = g.pending().into_data().iter::<f64>().collect();
        let names = ["loss".to_string(), "ego".to_string()];
        let peak = |parts: &[f32]| {
            Some(GradientPeak {
                name: format!("p{}", parts.len()),
                norm: f64::from(parts[1]).sqrt(),
                non_finite: usize::from(!parts[1].is_finite()),
                params: parts.len(),
            })
        };
        g.settle(&values, read_at, &names, peak)
    }

    #[test]
    fn skips_are_counted_on_the_device_and_reported_at_the_read() {
        let dev = Default::default();
        let mut g = Guard::<B>::new(NonFinite::Skip, 3, 1, 100, &dev);
        assert!(run(&mut g, &[(false, 1.0), (false, 2.0)], 102).unwrap().is_none());
        // The first skip since the read is the one reported; the streak runs on over reads.
        let r = run(&mut g, &[(false, 1.0), (true, f32::NAN), (true, 5.0)], 105)
            .unwrap()
            .unwrap();
        assert_eq!((r.skipped, r.streak, r.step), (2, 2, 104));
        assert!(
            r.what
                .starts_with("loss NaN, ego NaN; gradient norm NaN; the gradients of 1 of 3"),
            "{}",
            r.what
        );
        let e = run(&mut g, &[(true, 7.0)], 106).unwrap_err().to_string();
        assert!(
            e.contains("step 104:")
                && e.contains("3 steps in a row skipped (steps 104 to 106)")
                && e.contains("at step 106: loss 7.0000, ego 3.5000"),
            "{e}"
        );
        // A step that goes ahead ends the streak.
        let mut g = Guard::<B>::new(NonFinite::Skip, 2, 1, 0, &dev);
        let r = run(&mut g, &[(true, 9.0), (false, 1.0), (true, 9.0)], 3)
            .unwrap()
            .unwrap();
        assert_eq!((r.skipped, r.streak, r.step), (2, 1, 1));
        assert!(
            r.what.contains("largest gradient `p3` (norm 3.0000)"),
            "{}",
            r.what
        );
    }

    #[test]
    fn stop_latches_every_later_step_and_ends_the_run_at_the_read() {
        let dev = Default::default();
        let mut g = Guard::<B>::new(NonFinite::Stop, 10, 1, 0, &dev);
        let finite = |v: Option<Tensor<B, 1>>| v.unwrap().is_finite().all().into_scalar();
        assert!(finite(g.values(t(&[1.0]))));
        g.observe(t(&[1.0]), t(&[f32::NAN, 0.0]), t(&[1.0]), t(&[1.0]));
        assert!(
            !finite(g.values(t(&[1.0]))),
            "a finite loss no longer lets the step through"
        );
        let values: Vec<f64> = g.pending().into_data().iter::<f64>().collect();
        let e = g
            .settle(&values, 1, &["loss".into(), "ego".into()], |_| None)
            .unwrap_err();
        assert!(
            e.to_string().contains("step 1:") && e.to_string().contains("\"stop\""),
            "{e}"
        );
        // With several ranks the loss is no guard, the latch alone is.
        let g = Guard::<B>::new(NonFinite::Skip, 10, 2, 0, &dev);
        assert!(g.values(t(&[f32::NAN])).is_none());
    }
}
