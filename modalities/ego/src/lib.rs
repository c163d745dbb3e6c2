//! The ego-action modality: three tokens per frame for the ego motion since the previous frame
//! (`dx` forward, `dy` left, `dθ`, in the previous ego frame), each discretised into `bins` uniform bins
//! (paper supplementary B.1.1 and B.2.1).
//!
//! Defaults are the paper's ranges: dx ∈ [0, 10] m, dy ∈ [-0.5, 0.5] m, dθ ∈ [-0.25, 0.25] rad, 1024
//! bins. The official release uses dx ±10, dy ±4, dθ ±1; set them in the config to match it:
//!
//! ```toml
//! [modality.ego]
//! dx = [-10.0, 10.0]
//! dy = [-4.0, 4.0]
//! dtheta = [-1.0, 1.0]
//! ```

use serde::Deserialize;
use std::sync::Arc;
use umgen_modality::{
    ClampCount, DecodeReport, Discretizer, Modality, ModalityError, ModalitySpec, Result, ScalarBins,
    parse_settings,
};
use umgen_scene::{EgoAction, Frame, SceneClip, wrap_angle};

/// The kind name used in configs.
pub const KIND: &str = "ego";

/// Names of the three tokens, in order.
pub const FIELDS: [&str; 3] = ["dx", "dy", "dtheta"];

/// Settings of the ego modality (`[modality.<name>]`).
#[derive(Debug, Clone, PartialEq, Deserialize, serde::Serialize)]
#[serde(deny_unknown_fields, default)]
pub struct EgoConfig {
    /// Bins per value.
    pub bins: u32,
    /// Range of the forward displacement (m).
    pub dx: [f64; 2],
    /// Range of the leftward displacement (m).
    pub dy: [f64; 2],
    /// Range of the heading change (rad).
    pub dtheta: [f64; 2],
}

impl Default for EgoConfig {
    fn default() -> Self {
        Self {
            bins: 1024,
            dx: [0.0, 10.0],
            dy: [-0.5, 0.5],
            dtheta: [-0.25, 0.25],
        }
    }
}

/// The ego-action modality.
#[derive(Debug)]
pub struct EgoModality {
    spec: ModalitySpec,
    config: EgoConfig,
    bins: Discretizer,
}

impl EgoModality {
    /// An ego modality called `name`.
    pub fn new(name: &str, config: EgoConfig) -> Result<Self> {
        let ranges = [config.dx, config.dy, config.dtheta];
        let fields = FIELDS
            .iter()
            .zip(ranges)
            .map(|(f, [lo, hi])| {
                Ok((
                    f.to_string(),
                    ScalarBins::new(&format!("modality.{name}.{f}"), lo, hi, config.bins)?,
                ))
            })
            .collect::<Result<Vec<_>>>()?;
        // The bins go into the spec so that models can decode actions (AMA) without knowing this crate.
        let spec = ModalitySpec::new(name, KIND, config.bins, 3)
            .with_bins(fields.iter().map(|(_, b)| *b).collect())
            .with_ordinal(config.bins);
        Ok(Self {
            spec,
            config,
            bins: Discretizer::new(name, fields),
        })
    }

    /// Builds the modality from its config table; the factory registered under [`KIND`].
    pub fn factory(name: &str, table: &toml::Table) -> Result<Arc<dyn Modality>> {
        Ok(Arc::new(Self::new(name, parse_settings(name, table)?)?))
    }

    /// The settings in use.
    pub fn config(&self) -> &EgoConfig {
        &self.config
    }

    /// Tokens of one action.
    pub fn encode(&self, action: &EgoAction) -> Result<Vec<u32>> {
        let values = [action.dx, action.dy, wrap_angle(action.dtheta)];
        values
            .iter()
            .enumerate()
            .map(|(i, &v)| self.bins.encode(i, v))
            .collect()
    }

    /// The action at the bin centres of three tokens.
    pub fn decode(&self, ids: &[u32]) -> Result<EgoAction> {
        self.spec.check_frame_ids(ids)?;
        let mut v = [0.0; 3];
        for (i, (&id, out)) in ids.iter().zip(&mut v).enumerate() {
            *out = self
                .bins
                .decode(i, id)
                .ok_or_else(|| ModalityError::TokenOutOfVocab {
                    modality: self.spec.name.clone(),
                    position: i,
                    id,
                    allowed: format!("0..{}", self.config.bins),
                })?;
        }
        Ok(EgoAction::new(v[0], v[1], v[2]))
    }
}

impl Modality for EgoModality {
    fn spec(&self) -> &ModalitySpec {
        &self.spec
    }

    fn settings(&self) -> serde_json::Value {
        serde_json::to_value(&self.config).unwrap_or(serde_json::Value::Null)
    }

    fn tokenize(&self, clip: &SceneClip, t: usize) -> Result<Vec<u32>> {
        self.encode(&clip.frame(t)?.action)
    }

    fn detokenize(&self, ids: &[u32], frame: &mut Frame) -> Result<DecodeReport> {
        frame.action = self.decode(ids)?;
        Ok(DecodeReport::default())
    }

    fn clamp_report(&self) -> Vec<ClampCount> {
        self.bins.clamp_report()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{Rng, SeedableRng, rngs::StdRng};
    use umgen_scene::EgoPose;

    fn clip_of(actions: &[EgoAction]) -> SceneClip {
        let frames = actions
            .iter()
            .enumerate()
            .map(|(t, a)| Frame {
                time: t as f64 * 0.5,
                action: *a,
                ego: EgoPose::default(),
                ..Frame::default()
            })
            .collect();
        SceneClip::new("c", 0.5, frames).unwrap()
    }

    #[test]
    fn round_trip_within_half_a_bin_for_random_actions() {
        let ego = EgoModality::new("ego", EgoConfig::default()).unwrap();
        let mut rng = StdRng::seed_from_u64(3);
        let actions: Vec<_> = (0..2000)
            .map(|_| {
                EgoAction::new(
                    rng.random_range(0.0..10.0),
                    rng.random_range(-0.5..0.5),
                    rng.random_range(-0.25..0.25),
                )
            })
            .collect();
        let clip = clip_of(&actions);
        let ids = ego.tokenize_clip(&clip).unwrap();
        let half = [10.0 / 2048.0, 1.0 / 2048.0, 0.5 / 2048.0];
        for (a, id) in actions.iter().zip(&ids) {
            let mut f = Frame::default();
            ego.detokenize(id, &mut f).unwrap();
            for ((v, d), h) in a.to_array().iter().zip(f.action.to_array()).zip(half) {
                assert!((v - d).abs() <= h + 1e-12, "{v} vs {d}");
            }
        }
        assert!(ego.clamp_report().iter().all(|c| c.below == 0 && c.above == 0));
    }

    #[test]
    fn out_of_range_values_clamp_and_are_counted() {
        let ego = EgoModality::new("ego", EgoConfig::default()).unwrap();
        let clip = clip_of(&[EgoAction::new(12.0, -0.7, 0.0), EgoAction::new(-1.0, 0.0, 0.3)]);
        let ids = ego.tokenize_clip(&clip).unwrap();
        assert_eq!(ids[0], vec![1023, 0, 512]);
        assert_eq!(ids[1], vec![0, 512, 1023]);
        let r = ego.clamp_report();
        assert_eq!((r[0].below, r[0].above), (1, 1));
        assert_eq!((r[1].below, r[1].above), (1, 0));
        assert_eq!((r[2].below, r[2].above), (0, 1));
    }

    #[test]
    fn config_errors_name_the_key() {
        let table: toml::Table = toml::from_str("dx = [5.0, 1.0]").unwrap();
        let err = EgoModality::factory("ego", &table).unwrap_err().to_string();
        assert!(err.contains("modality.ego.dx"), "{err}");
        let table: toml::Table = toml::from_str("dz = [0.0, 1.0]").unwrap();
        let err = EgoModality::factory("ego", &table).unwrap_err().to_string();
        assert!(err.contains("modality.ego") && err.contains("dz"), "{err}");
        let table: toml::Table = toml::from_str("bins = \"many\"").unwrap();
        let err = EgoModality::factory("ego", &table).unwrap_err().to_string();
        assert!(err.contains("modality.ego.bins"), "{err}");
    }

    #[test]
    fn decode_rejects_ids_outside_the_bins() {
        let ego = EgoModality::new("ego", EgoConfig::default()).unwrap();
        assert!(
            ego.decode(&[0, 1024, 0])
                .unwrap_err()
                .to_string()
                .contains("1024")
        );
        assert!(ego.decode(&[0, 1]).is_err());
    }
}
