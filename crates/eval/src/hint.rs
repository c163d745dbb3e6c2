//! How a model uses the kinematic hint it is given. One step ahead, each agent the model places is either
//! on the bins of the hint (the binned constant-acceleration prediction `backbone.track_accel` feeds the
//! TAR) or moved off them. A model that learned more than the hint moves agents off it where that brings
//! them closer to where they went; one whose departures land farther away does worse than copying it.

use serde::Serialize;

/// The agents of one-step predictions split by whether the model kept them on the hint's bins, with
/// their errors (metres) against the true positions.
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize)]
pub struct HintUse {
    /// Agents found in the model's frame, the hint and the truth.
    pub agents: usize,
    /// Of them, placed where the hint puts them.
    pub followed: usize,
    /// Summed error of the followed agents (the model's and the hint's, which are equal).
    pub followed_error: f64,
    /// Summed error of the other agents as the model placed them.
    pub departed_error: f64,
    /// Summed error of the same agents as the hint placed them.
    pub departed_hint_error: f64,
    /// Departures nearer the truth than the hint.
    pub closer: usize,
    /// Departures farther from the truth than the hint.
    pub farther: usize,
}

impl HintUse {
    /// Splits the agents (global positions by track id) of `model` by whether they lie within `same_m`
    /// of the `hint`'s, and scores both against `truth`. Agents missing from any of the three are left
    /// out.
    pub fn of(
        model: &[(u64, [f64; 2])],
        hint: &[(u64, [f64; 2])],
        truth: &[(u64, [f64; 2])],
        same_m: f64,
    ) -> Self {
        let find = |v: &[(u64, [f64; 2])], id: u64| v.iter().find(|(i, _)| *i == id).map(|(_, p)| *p);
        let dist = |a: [f64; 2], b: [f64; 2]| (a[0] - b[0]).hypot(a[1] - b[1]);
        let mut out = Self::default();
        for (id, m) in model {
            let (Some(h), Some(t)) = (find(hint, *id), find(truth, *id)) else {
                continue;
            };
            out.agents += 1;
            let (em, eh) = (dist(*m, t), dist(h, t));
            if dist(*m, h) <= same_m {
                out.followed += 1;
                out.followed_error += em;
            } else {
                out.departed_error += em;
                out.departed_hint_error += eh;
                out.closer += usize::from(em < eh);
                out.farther += usize::from(em > eh);
            }
        }
        out
    }

    /// Adds another set of agents.
    pub fn add(&mut self, o: &Self) {
        self.agents += o.agents;
        self.followed += o.followed;
        self.followed_error += o.followed_error;
        self.departed_error += o.departed_error;
        self.departed_hint_error += o.departed_hint_error;
        self.closer += o.closer;
        self.farther += o.farther;
    }

    /// Agents the model moved off the hint.
    pub fn departed(&self) -> usize {
        self.agents - self.followed
    }

    /// The mean error of all agents had the model copied the hint everywhere.
    pub fn hint_error(&self) -> Option<f64> {
        (self.agents > 0).then(|| (self.followed_error + self.departed_hint_error) / self.agents as f64)
    }

    /// Shares and mean errors, as `umgen eval` reports them.
    pub fn summary(&self) -> HintSummary {
        let share = |n: usize, of: usize| (of > 0).then(|| n as f64 / of as f64);
        let mean = |sum: f64, of: usize| (of > 0).then(|| sum / of as f64);
        let d = self.departed();
        HintSummary {
            agents: self.agents,
            followed: share(self.followed, self.agents),
            followed_error: mean(self.followed_error, self.followed),
            departed: share(d, self.agents),
            departed_error: mean(self.departed_error, d),
            departed_hint_error: mean(self.departed_hint_error, d),
            closer: share(self.closer, d),
            farther: share(self.farther, d),
            hint_error: self.hint_error(),
        }
    }
}

/// [`HintUse`] as shares of agents and mean errors (metres); `None` where nothing is averaged.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct HintSummary {
    /// Agents scored.
    pub agents: usize,
    /// Share on the hint's bins.
    pub followed: Option<f64>,
    /// Their mean error.
    pub followed_error: Option<f64>,
    /// Share moved off the hint.
    pub departed: Option<f64>,
    /// Their mean error as the model placed them.
    pub departed_error: Option<f64>,
    /// Their mean error as the hint placed them.
    pub departed_hint_error: Option<f64>,
    /// Share of departures nearer the truth than the hint.
    pub closer: Option<f64>,
    /// Share of departures farther from it.
    pub farther: Option<f64>,
    /// Mean error of all agents had the model copied the hint.
    pub hint_error: Option<f64>,
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn agents_split_by_the_hint_and_scored_against_the_truth() {
        let truth = [
            (0, [0.0, 0.0]),
            (1, [10.0, 0.0]),
            (2, [20.0, 0.0]),
            (3, [30.0, 0.0]),
        ];
        let hint = [
            (0, [0.0, 0.0]),
            (1, [10.5, 0.0]),
            (2, [20.0, 0.25]),
            (3, [30.0, 0.0]),
        ];
        // 0 follows exactly and 3 within the tolerance; 1 departs to 0.125 m from the truth (the hint is
        // 0.5 m off: closer), 2 to 1.0 m (the hint 0.25 m: farther); 9 is in the model's frame only.
        let model = [
            (0, [0.0, 0.0]),
            (1, [10.125, 0.0]),
            (2, [19.0, 0.0]),
            (3, [30.0, 1e-9]),
            (9, [5.0, 5.0]),
        ];
        let u = HintUse::of(&model, &hint, &truth, 1e-6);
        assert_eq!((u.agents, u.followed, u.departed()), (4, 2, 2));
        assert_eq!((u.closer, u.farther), (1, 1));
        assert!((u.followed_error - 1e-9).abs() < 1e-12);
        assert!((u.departed_error - 1.125).abs() < 1e-12);
        assert!((u.departed_hint_error - 0.75).abs() < 1e-12);
        // Copying the hint: (0 + 0.5 + 0.25 + 0) / 4.
        assert!((u.hint_error().unwrap_or(f64::NAN) - 0.1875).abs() < 1e-9);

        let mut twice = u;
        twice.add(&u);
        assert_eq!((twice.agents, twice.followed, twice.closer), (8, 4, 2));
        let s = twice.summary();
        assert_eq!(s.followed, Some(0.5));
        assert_eq!(s.departed_error, Some(0.5625));
        assert_eq!(s.departed_hint_error, Some(0.375));
        assert_eq!((s.closer, s.farther), (Some(0.5), Some(0.5)));
    }

    #[test]
    fn no_agents_gives_no_means() {
        let u = HintUse::of(&[(0, [0.0, 0.0])], &[], &[(0, [0.0, 0.0])], 1e-6);
        assert_eq!(u, HintUse::default());
        let s = u.summary();
        assert_eq!(s.agents, 0);
        assert!(s.followed.is_none() && s.hint_error.is_none() && s.closer.is_none());
    }
}
