//! Slots of stop points a modality declares (`backbone.track_stops`): where tracked objects are to stop.

use serde::{Deserialize, Serialize};

/// Slots of stop points (a traffic light's stop line while it shows red): fixed-size groups of tokens,
/// each a place in the frame's ego coordinates and a state, before which tracked objects heading its way
/// are to stop while the state says so (`backbone.track_stops`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Stops {
    /// Tokens per slot.
    pub slot: usize,
    /// Ids `0..values` are value bins; a slot whose `x` token is not one (a pad) holds no point.
    pub values: u32,
    /// Position in the slot and bins of `x`, `y` (m) and the heading (rad) of the direction of travel
    /// that stops there, in that order.
    pub fields: [(usize, crate::scalar::ScalarBins); 3],
    /// Position of the state token in the slot.
    pub state: usize,
    /// State ids that ask to stop (red), at most [`Stops::MAX_IDS`].
    pub stop: Vec<u32>,
    /// State ids that release every stop at the same place (the same x and y ids): a stop line where
    /// one movement is red and another green lets traffic through. At most [`Stops::MAX_IDS`].
    pub go: Vec<u32>,
}

impl Stops {
    /// Most state ids in [`Stops::stop`] and in [`Stops::go`] (the generation kernels' fixed arrays).
    pub const MAX_IDS: usize = 4;

    /// Why slots of `tokens` content ids `0..vocab` cannot hold these stop points, if they cannot.
    pub(crate) fn check(&self, tokens: usize, vocab: u32) -> Result<(), String> {
        if self.slot == 0 || !tokens.is_multiple_of(self.slot) {
            return Err(format!(
                "stop slots of {} tokens do not divide {tokens} tokens",
                self.slot
            ));
        }
        let places = self.fields.iter().map(|(i, _)| *i).chain([self.state]);
        if let Some(i) = places.clone().find(|&i| i >= self.slot) {
            return Err(format!(
                "stop slot position {i} is outside a slot of {}",
                self.slot
            ));
        }
        for (what, ids) in [("stop", &self.stop), ("go", &self.go)] {
            if ids.len() > Self::MAX_IDS || (what == "stop" && ids.is_empty()) {
                return Err(format!(
                    "{} {what} state ids (1 to {} allowed)",
                    ids.len(),
                    Self::MAX_IDS
                ));
            }
            if let Some(id) = ids.iter().find(|&&id| id < self.values || id >= vocab) {
                return Err(format!(
                    "{what} state id {id} is not a state (ids {}..{vocab})",
                    self.values
                ));
            }
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::ModalitySpec;
    use crate::scalar::ScalarBins;

    /// Lights-like stop slots of 4 tokens: x, y, heading in 128 bins, state 128 + code.
    fn lights(stop: Vec<u32>, go: Vec<u32>) -> Stops {
        let bins = |lo, hi| ScalarBins::new("k", lo, hi, 128).unwrap();
        Stops {
            slot: 4,
            values: 128,
            fields: [
                (0, bins(-64.0, 64.0)),
                (1, bins(-64.0, 64.0)),
                (2, bins(-3.2, 3.2)),
            ],
            state: 3,
            stop,
            go,
        }
    }

    #[test]
    fn stop_slots_are_checked_against_the_spec() {
        let spec = |stops: Stops, tokens: usize| {
            ModalitySpec::new("lights", "traffic_light", 133, tokens).with_stops(stops)
        };
        assert!(spec(lights(vec![129], vec![130, 131]), 32).validate().is_ok());
        let cases = [
            (spec(lights(vec![129], vec![]), 30), "do not divide 30"),
            (spec(lights(vec![], vec![131]), 32), "0 stop state ids"),
            (
                spec(lights(vec![5], vec![131]), 32),
                "stop state id 5 is not a state",
            ),
            (spec(lights(vec![129], vec![140]), 32), "go state id 140"),
            (
                spec(lights(vec![129], vec![128, 129, 130, 131, 132]), 32),
                "5 go state ids",
            ),
            (
                spec(
                    Stops {
                        state: 4,
                        ..lights(vec![129], vec![])
                    },
                    32,
                ),
                "position 4 is outside",
            ),
        ];
        for (s, needle) in cases {
            let err = s.validate().unwrap_err().to_string();
            assert!(
                err.contains(needle) && err.contains("`lights`"),
                "{needle}: {err}"
            );
        }
    }
}
