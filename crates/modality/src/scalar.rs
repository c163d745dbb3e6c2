//! Scalar discretisation (supplementary B.1.1 of the paper) with clamp counting.
//!
//! `v_norm = (v - lo) / (hi - lo)`, `id = clamp(floor(v_norm · bins), 0, bins - 1)`, decoded to the bin
//! centre. Values below `lo` or above `hi` clamp to the first or last bin and are counted, so that a
//! range that is too narrow for the data shows up in the logs instead of silently distorting it.

use crate::error::{ModalityError, Result};
use serde::{Deserialize, Serialize};
use std::sync::atomic::{AtomicU64, Ordering};

/// Uniform bins over `[lo, hi]`.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct ScalarBins {
    /// Lower bound.
    pub lo: f64,
    /// Upper bound.
    pub hi: f64,
    /// Number of bins.
    pub bins: u32,
}

/// Which side a value was clamped on.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Clamp {
    /// Below `lo`.
    Below,
    /// Above `hi`.
    Above,
}

impl ScalarBins {
    /// Bins over `[lo, hi]`; `key` names the config entry in errors.
    pub fn new(key: &str, lo: f64, hi: f64, bins: u32) -> Result<Self> {
        if !(lo.is_finite() && hi.is_finite() && lo < hi) {
            return Err(ModalityError::Config {
                key: key.into(),
                message: format!("range [{lo}, {hi}] needs finite bounds with lo < hi"),
            });
        }
        if bins < 2 {
            return Err(ModalityError::Config {
                key: key.into(),
                message: format!("{bins} bins; need at least 2"),
            });
        }
        Ok(Self { lo, hi, bins })
    }

    /// Width of one bin.
    pub fn width(&self) -> f64 {
        (self.hi - self.lo) / f64::from(self.bins)
    }

    /// The bin of a finite value and whether it was clamped. `v == hi` falls in the last bin unclamped.
    pub fn encode(&self, v: f64) -> (u32, Option<Clamp>) {
        let last = self.bins - 1;
        if v < self.lo {
            return (0, Some(Clamp::Below));
        }
        if v > self.hi {
            return (last, Some(Clamp::Above));
        }
        let norm = (v - self.lo) / (self.hi - self.lo);
        // The float-to-int cast saturates; `min` keeps v == hi in the last bin.
        let id = ((norm * f64::from(self.bins)).floor() as u32).min(last);
        (id, None)
    }

    /// The centre of bin `id`, or `None` when `id` is not a bin.
    pub fn decode(&self, id: u32) -> Option<f64> {
        (id < self.bins).then(|| self.lo + (f64::from(id) + 0.5) * self.width())
    }
}

/// How many values of one field were clamped.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct ClampCount {
    /// Field name (for example `dx`).
    pub field: String,
    /// Values below the range.
    pub below: u64,
    /// Values above the range.
    pub above: u64,
}

#[derive(Debug)]
struct Field {
    name: String,
    bins: ScalarBins,
    below: AtomicU64,
    above: AtomicU64,
}

/// A set of named fields, each with its own bins and clamp counters. Counting is thread-safe, so one
/// tokenizer can serve parallel workers.
#[derive(Debug)]
pub struct Discretizer {
    modality: String,
    fields: Vec<Field>,
}

impl Discretizer {
    /// A discretiser for `modality` over named fields.
    pub fn new(modality: impl Into<String>, fields: Vec<(String, ScalarBins)>) -> Self {
        let fields = fields
            .into_iter()
            .map(|(name, bins)| Field {
                name,
                bins,
                below: AtomicU64::new(0),
                above: AtomicU64::new(0),
            })
            .collect();
        Self {
            modality: modality.into(),
            fields,
        }
    }

    /// Number of fields.
    pub fn len(&self) -> usize {
        self.fields.len()
    }

    /// Whether there are no fields.
    pub fn is_empty(&self) -> bool {
        self.fields.is_empty()
    }

    /// Bins of field `i`.
    pub fn bins(&self, i: usize) -> Option<&ScalarBins> {
        self.fields.get(i).map(|f| &f.bins)
    }

    /// Field names in order.
    pub fn names(&self) -> impl Iterator<Item = &str> {
        self.fields.iter().map(|f| f.name.as_str())
    }

    /// Token of value `v` for field `i`, counting clamps; non-finite values are an error.
    pub fn encode(&self, i: usize, v: f64) -> Result<u32> {
        let field = self.fields.get(i).ok_or_else(|| ModalityError::Tokenizer {
            modality: self.modality.clone(),
            message: format!("no scalar field {i}"),
        })?;
        if !v.is_finite() {
            return Err(ModalityError::NonFinite {
                modality: self.modality.clone(),
                field: field.name.clone(),
                value: v,
            });
        }
        let (id, clamp) = field.bins.encode(v);
        match clamp {
            Some(Clamp::Below) => field.below.fetch_add(1, Ordering::Relaxed),
            Some(Clamp::Above) => field.above.fetch_add(1, Ordering::Relaxed),
            None => 0,
        };
        Ok(id)
    }

    /// Bin centre of token `id` for field `i`; `None` when `id` is not a bin of that field.
    pub fn decode(&self, i: usize, id: u32) -> Option<f64> {
        self.fields.get(i).and_then(|f| f.bins.decode(id))
    }

    /// Clamp counts so far, one entry per field.
    pub fn clamp_report(&self) -> Vec<ClampCount> {
        self.fields
            .iter()
            .map(|f| ClampCount {
                field: f.name.clone(),
                below: f.below.load(Ordering::Relaxed),
                above: f.above.load(Ordering::Relaxed),
            })
            .collect()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{Rng, SeedableRng, rngs::StdRng};

    #[test]
    fn paper_formula_on_hand_computed_values() {
        let b = ScalarBins::new("x", -64.0, 64.0, 1024).unwrap();
        assert_eq!(b.width(), 0.125);
        assert_eq!(b.encode(-64.0), (0, None));
        assert_eq!(b.encode(0.0), (512, None));
        assert_eq!(b.encode(-0.0625), (511, None));
        assert_eq!(b.encode(10.0), (592, None)); // floor(74 / 0.125)
        assert_eq!(b.encode(64.0), (1023, None));
        assert_eq!(b.encode(64.01), (1023, Some(Clamp::Above)));
        assert_eq!(b.encode(-70.0), (0, Some(Clamp::Below)));
        assert_eq!(b.decode(592), Some(10.0625));
        assert_eq!(b.decode(1024), None);
    }

    #[test]
    fn round_trip_within_half_a_bin() {
        let mut rng = StdRng::seed_from_u64(1);
        for (lo, hi) in [(-64.0, 64.0), (0.0, 10.0), (-0.25, 0.25), (-0.3, 0.3)] {
            let b = ScalarBins::new("f", lo, hi, 1024).unwrap();
            for _ in 0..10_000 {
                let v = rng.random_range(lo..=hi);
                let (id, clamp) = b.encode(v);
                assert!(clamp.is_none());
                let d = b.decode(id).unwrap();
                assert!((d - v).abs() <= b.width() / 2.0 + 1e-12, "{v} -> {id} -> {d}");
                assert_eq!(b.encode(d).0, id, "bin centres encode to their own bin");
            }
        }
    }

    #[test]
    fn discretizer_counts_clamps_and_rejects_nan() {
        let d = Discretizer::new(
            "ego",
            vec![("dx".into(), ScalarBins::new("dx", 0.0, 10.0, 1024).unwrap())],
        );
        assert_eq!(d.encode(0, 11.0).unwrap(), 1023);
        assert_eq!(d.encode(0, -1.0).unwrap(), 0);
        assert_eq!(d.encode(0, -2.0).unwrap(), 0);
        assert_eq!(d.encode(0, 5.0).unwrap(), 512);
        assert_eq!(
            d.clamp_report(),
            vec![ClampCount {
                field: "dx".into(),
                below: 2,
                above: 1
            }]
        );
        let err = d.encode(0, f64::NAN).unwrap_err().to_string();
        assert!(
            err.contains("ego") && err.contains("dx") && err.contains("NaN"),
            "{err}"
        );
    }

    #[test]
    fn bad_ranges_name_the_key() {
        let err = ScalarBins::new("modality.ego.dx", 1.0, 1.0, 1024)
            .unwrap_err()
            .to_string();
        assert!(err.contains("modality.ego.dx"), "{err}");
        assert!(ScalarBins::new("k", 0.0, 1.0, 1).is_err());
    }
}
