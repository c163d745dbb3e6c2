//! The targets part of `umgen eval`: which of the bars the project holds generators to
//! ([`umgen_eval::targets`]) a run meets, from what the rest of the evaluation measured, and their table
//! in `report.md`.

use std::fmt::Write as _;
use umgen_eval::targets::{self, Check};

/// What kind of run is evaluated.
pub(super) struct Run {
    /// Clips continued.
    pub contexts: usize,
    /// Seconds generated (the shortest scene's).
    pub seconds: f64,
    /// Whether the ego followed its recorded actions (`generate --recorded-ego`).
    pub recorded_ego: bool,
}

/// The targets for `run`: a rollout of the model's own ego is held to the rollout targets (`rollout`,
/// checked against the horizon's statistics) and the map's (from the report's `map`); a step from the
/// recorded ego to the one-step target (from the first row of `l2`). Each kind leaves the other's
/// targets unmeasured, saying which run measures them.
pub(super) fn targets(
    run: &Run,
    rollout: Vec<Check>,
    l2: &[serde_json::Value],
    map: &serde_json::Value,
) -> Vec<Check> {
    let one_step = l2
        .first()
        .filter(|_| run.recorded_ego)
        .filter(|r| r["horizon"].as_u64() == Some(1))
        .and_then(|r| {
            Some((
                r["agents_model"].as_f64()?,
                r["agents_real_state_constant_acceleration"].as_f64()?,
            ))
        });
    if run.recorded_ego {
        let rollout = rollout
            .into_iter()
            .map(|c| Check::unmeasured(c.target, c.bar, "a rollout of the model's own ego measures it"));
        return std::iter::once(targets::one_step(one_step))
            .chain(rollout)
            .collect();
    }
    let mut checks = vec![targets::setup(run.contexts, run.seconds, run.recorded_ego)];
    checks.extend(rollout);
    checks.push(map_check(map));
    checks.push(targets::one_step(None));
    checks
}

/// The map target from the report's `map` (`null` without a map modality).
fn map_check(map: &serde_json::Value) -> Check {
    let layers: Vec<String> = map["layers"]
        .as_array()
        .map(|l| l.iter().filter_map(|v| v.as_str().map(String::from)).collect())
        .unwrap_or_default();
    let ious = |v: &serde_json::Value| -> Vec<Option<f64>> {
        v["iou"]
            .as_array()
            .map(|a| a.iter().map(serde_json::Value::as_f64).collect())
            .unwrap_or_default()
    };
    let seconds = map["seconds"].as_array().map_or(&[][..], |s| &s[..]);
    let (second, last) = match seconds.last() {
        Some(r) => (r["second"].as_u64().unwrap_or(0) as usize, ious(r)),
        None => (0, Vec::new()),
    };
    targets::map_iou(&layers, &last, &ious(&map["context"]), second)
}

/// The targets table of `report.md` (`targets`: the report's list).
pub(super) fn targets_markdown(md: &mut String, targets: &serde_json::Value) -> std::fmt::Result {
    let Some(rows) = targets.as_array().filter(|r| !r.is_empty()) else {
        return Ok(());
    };
    writeln!(
        md,
        "\n## Against the targets\n\nThe bars the project holds generators to (evaluation.md), checked against \
         what this run measured; a target another kind of run measures says which.\n"
    )?;
    writeln!(md, "| target | bar | measured | met |\n|---|---|---|---|")?;
    for r in rows {
        let met = match r["met"].as_bool() {
            Some(true) => "yes",
            Some(false) => "**no**",
            None => "-",
        };
        let text = |k: &str| r[k].as_str().unwrap_or("").replace('|', "\\|");
        writeln!(
            md,
            "| {} | {} | {} | {met} |",
            text("target"),
            text("bar"),
            text("measured")
        )?;
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]
    use super::*;

    fn run(recorded_ego: bool) -> Run {
        Run {
            contexts: 64,
            seconds: 30.0,
            recorded_ego,
        }
    }

    #[test]
    fn a_recorded_ego_step_is_held_to_the_one_step_target_alone() {
        let l2 = [serde_json::json!({
            "horizon": 1, "agents_model": 0.0943, "agents_real_state_constant_acceleration": 0.0970,
        })];
        let rollout = vec![targets::rate_ratio("collision rate", Some(0.01), Some(0.5))];
        let checks = targets(&run(true), rollout, &l2, &serde_json::Value::Null);
        assert_eq!(checks[0].target, "one step ahead");
        assert_eq!(checks[0].met, Some(true), "{:?}", checks[0]);
        assert_eq!(checks[1].target, "collision rate");
        assert_eq!(checks[1].met, None, "a recorded ego's rollout is not judged");
    }

    #[test]
    fn a_rollout_is_held_to_its_setup_the_rollout_targets_and_the_map() {
        let map = serde_json::json!({
            "layers": ["lane", "stop line"],
            "context": {"iou": [0.87, 0.29]},
            "seconds": [{"second": 1, "iou": [0.9, 0.9]}, {"second": 30, "iou": [0.82, 0.31]}],
        });
        let rollout = vec![targets::rate_ratio("collision rate", Some(0.01), Some(0.0125))];
        let checks = targets(&run(false), rollout, &[], &map);
        let names: Vec<_> = checks.iter().map(|c| c.target).collect();
        assert_eq!(
            names,
            [
                "rollout",
                "collision rate",
                "map at the generated pose",
                "one step ahead"
            ]
        );
        assert_eq!(checks[0].met, Some(true));
        assert_eq!(checks[1].met, Some(true));
        assert_eq!(checks[2].met, Some(false), "the stop lines are at 0.31");
        assert!(
            checks[2].measured.starts_with("second 30"),
            "{}",
            checks[2].measured
        );
        assert_eq!(checks[3].met, None);
        let mut md = String::new();
        targets_markdown(&mut md, &serde_json::to_value(&checks).unwrap()).unwrap();
        assert!(
            md.contains("| map at the generated pose |") && md.contains("| **no** |"),
            "{md}"
        );
    }
}
