//! The rollout targets a generator is held to (the project's acceptance for long rollouts), each checked
//! against what `umgen eval` measured: a [`Check`] per target, with the bar, the measured value and
//! whether it is met (`None` where the run does not measure it).
//!
//! The targets, for 64 or more held-out clips continued 30 s by top-k sampling with the model's own ego:
//! agents per frame within ±15 % of the real split's at every second; entries and exits per second
//! within ±25 %; collision and off-road rates at most 1.25× the real ones over the whole horizon; the
//! median heading–motion angle within 5° of the real one; one step ahead (greedy, recorded ego) the
//! agents' mean L2 below constant acceleration from the recorded state; every map layer's IoU at the
//! generated pose at least 0.8 at the horizon's last second.

use crate::horizon::Summary;
use serde::Serialize;

/// One target against a run.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Check {
    /// What is held to a bar.
    pub target: &'static str,
    /// The bar, in words and numbers.
    pub bar: String,
    /// What the run measured.
    pub measured: String,
    /// Whether the bar is met; `None` where the run does not measure it.
    pub met: Option<bool>,
}

impl Check {
    fn new(target: &'static str, bar: String, measured: String, met: Option<bool>) -> Self {
        Self {
            target,
            bar,
            measured,
            met,
        }
    }

    /// A target this run does not measure, and what would.
    pub fn unmeasured(target: &'static str, bar: String, why: &str) -> Self {
        Self::new(target, bar, why.to_string(), None)
    }
}

/// Contexts a rollout target is measured over, at the fewest.
pub const MIN_CONTEXTS: usize = 64;
/// Seconds a rollout target is measured over, at the fewest.
pub const MIN_SECONDS: f64 = 30.0;
/// Agents per frame: the largest relative distance from the real mean at any second.
pub const AGENTS_BAND: f64 = 0.15;
/// Entries and exits per second: the largest relative distance from the real rate.
pub const EVENTS_BAND: f64 = 0.25;
/// Collision and off-road rates: the largest ratio to the real ones.
pub const RATE_RATIO: f64 = 1.25;
/// Heading against motion: the largest distance of the median from the real one, degrees.
pub const HEADING_DEG: f64 = 5.0;
/// Map layers' IoU at the generated pose at the horizon's last second: the least.
pub const MAP_IOU: f64 = 0.8;

/// The rollout the targets are read from: `contexts` clips continued `seconds`, with the model's own ego
/// unless `recorded_ego`.
pub fn setup(contexts: usize, seconds: f64, recorded_ego: bool) -> Check {
    let met = contexts >= MIN_CONTEXTS && seconds >= MIN_SECONDS && !recorded_ego;
    let ego = if recorded_ego { "recorded ego" } else { "own ego" };
    Check::new(
        "rollout",
        format!("≥ {MIN_CONTEXTS} held-out clips continued ≥ {MIN_SECONDS:.0} s, the model's own ego"),
        format!("{contexts} clips, {seconds:.1} s, {ego}"),
        Some(met),
    )
}

/// The rollout's targets from its statistics: the real split's (`real`), each second's and the whole
/// horizon's (`whole`, every generated frame pooled).
pub fn rollout(real: &Summary, seconds: &[Summary], whole: &Summary) -> Vec<Check> {
    let per_second = |f: fn(&Summary) -> Option<f64>| seconds.iter().map(f).collect::<Vec<_>>();
    let intervals = |f: fn(&Summary) -> Option<[f64; 2]>| seconds.iter().map(f).collect::<Vec<_>>();
    vec![
        agents_per_frame(real.agents_mean, &per_second(|s| s.agents_mean)),
        event_rate(
            "entries per second",
            real.entries_per_s,
            whole.entries_per_s,
            &intervals(|s| s.counts.entries_per_s_95),
        ),
        event_rate(
            "exits per second",
            real.exits_per_s,
            whole.exits_per_s,
            &intervals(|s| s.counts.exits_per_s_95),
        ),
        rate_ratio("collision rate", real.collision_rate, whole.collision_rate),
        rate_ratio("off-road rate", real.off_road_rate, whole.off_road_rate),
        heading_motion(real.heading_motion_median_deg, whole.heading_motion_median_deg),
    ]
}

/// Agents per frame at each second (`None` for a second without frames) against the real mean.
pub fn agents_per_frame(real: Option<f64>, seconds: &[Option<f64>]) -> Check {
    let Some(real) = real.filter(|r| *r > 0.0) else {
        let bar = format!(
            "within ±{:.0} % of the real mean at every second",
            AGENTS_BAND * 100.0
        );
        return Check::unmeasured("agents per frame", bar, "the real split holds no agents");
    };
    let bar = format!(
        "within ±{:.0} % of the real {real:.2} at every second",
        AGENTS_BAND * 100.0
    );
    let ratios: Vec<(usize, f64)> = seconds
        .iter()
        .enumerate()
        .filter_map(|(i, m)| m.map(|m| (i + 1, m / real)))
        .collect();
    let Some(&(worst_s, worst)) = ratios
        .iter()
        .max_by(|a, b| (a.1 - 1.0).abs().total_cmp(&(b.1 - 1.0).abs()))
    else {
        return Check::unmeasured("agents per frame", bar, "no generated frames");
    };
    let (lo, hi) = ratios
        .iter()
        .fold((f64::INFINITY, f64::NEG_INFINITY), |(lo, hi), (_, r)| {
            (lo.min(*r), hi.max(*r))
        });
    let measured = format!(
        "×{lo:.2} to ×{hi:.2} of the real mean; farthest at second {worst_s} ({:.2})",
        worst * real
    );
    Check::new(
        "agents per frame",
        bar,
        measured,
        Some((worst - 1.0).abs() <= AGENTS_BAND),
    )
}

/// A rate of events per second (entries or exits, `what`): the pooled rate over the horizon and each
/// second's 95 % interval against the real rate. A second is off the target where its whole interval
/// lies outside the band around the real rate (a second of a 64-scene rollout holds a few dozen events,
/// so its own rate moves by about ±20 % between rollouts); the target is met when the pooled rate lies in
/// the band and no second is off it.
pub fn event_rate(
    what: &'static str,
    real: Option<f64>,
    pooled: Option<f64>,
    seconds: &[Option<[f64; 2]>],
) -> Check {
    let Some(real) = real else {
        let bar = format!("within ±{:.0} % of the real rate", EVENTS_BAND * 100.0);
        return Check::unmeasured(what, bar, "no real transitions");
    };
    let bar = format!(
        "within ±{:.0} % of the real {real:.3}/s (pooled, and no second's 95 % interval outside the band)",
        EVENTS_BAND * 100.0
    );
    let Some(pooled) = pooled else {
        return Check::unmeasured(what, bar, "no generated transitions");
    };
    let (lo, hi) = (real * (1.0 - EVENTS_BAND), real * (1.0 + EVENTS_BAND));
    let off: Vec<usize> = seconds
        .iter()
        .enumerate()
        .filter_map(|(i, ci)| ci.filter(|[a, b]| *b < lo || *a > hi).map(|_| i + 1))
        .collect();
    let in_band = (lo..=hi).contains(&pooled);
    let ratio = if real > 0.0 {
        format!(" (×{:.2})", pooled / real)
    } else {
        String::new()
    };
    let listed: Vec<String> = off.iter().map(|s| s.to_string()).collect();
    let seconds_off = match off.len() {
        0 => "no second off it".to_string(),
        _ => format!("off it at second(s) {}", listed.join(", ")),
    };
    let measured = format!("{pooled:.3}/s pooled{ratio}; {seconds_off}");
    Check::new(what, bar, measured, Some(in_band && off.is_empty()))
}

/// A rate (`what`) over the whole horizon at most [`RATE_RATIO`] times the real one.
pub fn rate_ratio(what: &'static str, real: Option<f64>, generated: Option<f64>) -> Check {
    let Some(real) = real else {
        return Check::unmeasured(
            what,
            format!("≤ {RATE_RATIO}× the real rate"),
            "no real rate (no maps?)",
        );
    };
    let bar = format!("≤ {RATE_RATIO}× the real {real:.4}, over the whole horizon");
    let Some(g) = generated else {
        return Check::unmeasured(what, bar, "no generated rate");
    };
    let ratio = if real > 0.0 {
        format!(" (×{:.2})", g / real)
    } else {
        String::new()
    };
    Check::new(what, bar, format!("{g:.4}{ratio}"), Some(g <= RATE_RATIO * real))
}

/// The median angle between heading and motion of moving agents over the whole horizon, within
/// [`HEADING_DEG`] of the real one.
pub fn heading_motion(real: Option<f64>, generated: Option<f64>) -> Check {
    let what = "heading against motion";
    let bar = match real {
        Some(r) => format!("median within {HEADING_DEG:.0}° of the real {r:.2}°"),
        None => format!("median within {HEADING_DEG:.0}° of the real one"),
    };
    match (real, generated) {
        (Some(r), Some(g)) => Check::new(what, bar, format!("{g:.2}°"), Some((g - r).abs() <= HEADING_DEG)),
        _ => Check::unmeasured(what, bar, "no moving agents on one side"),
    }
}

/// One step ahead: the agents' mean L2 of the model against constant acceleration from the recorded
/// state; `None` for a run that is not one greedy step from the recorded ego.
pub fn one_step(errors: Option<(f64, f64)>) -> Check {
    let what = "one step ahead";
    let bar = "agents' mean L2 below constant acceleration from the recorded state".to_string();
    match errors {
        Some((model, ca)) => Check::new(
            what,
            bar,
            format!("{model:.4} m against {ca:.4} m"),
            Some(model < ca),
        ),
        None => Check::unmeasured(
            what,
            bar,
            "a run of `--frames 1 --recorded-ego --top-k 1` measures it",
        ),
    }
}

/// Each map layer's IoU at the generated pose at the horizon's last second (`last`), with the context
/// frames' (what the tokenizer keeps of the real map, `context`), against [`MAP_IOU`].
pub fn map_iou(layers: &[String], last: &[Option<f64>], context: &[Option<f64>], second: usize) -> Check {
    let what = "map at the generated pose";
    let bar = format!("every layer's IoU ≥ {MAP_IOU} at the last second");
    if layers.is_empty() || last.iter().all(Option::is_none) {
        return Check::unmeasured(what, bar, "no map decoded at the last second");
    }
    let cell = |v: Option<f64>| v.map_or("-".to_string(), |x| format!("{x:.2}"));
    let parts: Vec<String> = layers
        .iter()
        .enumerate()
        .map(|(i, name)| {
            let (l, c) = (last.get(i).copied().flatten(), context.get(i).copied().flatten());
            format!("{name} {} (context {})", cell(l), cell(c))
        })
        .collect();
    let met = last.len() == layers.len() && last.iter().all(|v| v.is_some_and(|x| x >= MAP_IOU));
    Check::new(
        what,
        bar,
        format!("second {second}: {}", parts.join(", ")),
        Some(met),
    )
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn agents_per_frame_fails_on_any_second_outside_the_band() {
        let ok = agents_per_frame(Some(8.0), &[Some(7.0), None, Some(9.1)]);
        assert_eq!(ok.met, Some(true), "{ok:?}");
        assert!(ok.measured.contains("second 3"), "{}", ok.measured);
        // 6.7 is 16 % under 8.0.
        let off = agents_per_frame(Some(8.0), &[Some(8.0), Some(6.7), Some(8.2)]);
        assert_eq!(off.met, Some(false));
        assert!(
            off.measured.contains("second 2") && off.measured.contains("6.70"),
            "{}",
            off.measured
        );
        assert_eq!(agents_per_frame(Some(8.0), &[None]).met, None);
        assert_eq!(agents_per_frame(Some(0.0), &[Some(1.0)]).met, None);
    }

    #[test]
    fn an_event_rate_is_off_only_where_the_whole_interval_misses_the_band() {
        // Real 0.4/s: band 0.3–0.5.
        let inside = event_rate(
            "entries",
            Some(0.4),
            Some(0.45),
            &[Some([0.2, 0.6]), Some([0.45, 0.7])],
        );
        assert_eq!(inside.met, Some(true), "{inside:?}");
        let second_off = event_rate(
            "entries",
            Some(0.4),
            Some(0.45),
            &[Some([0.2, 0.6]), Some([0.51, 0.9])],
        );
        assert_eq!(second_off.met, Some(false));
        assert!(
            second_off.measured.contains("second(s) 2"),
            "{}",
            second_off.measured
        );
        let pooled_off = event_rate("exits", Some(0.4), Some(0.52), &[None]);
        assert_eq!(pooled_off.met, Some(false));
        assert!(pooled_off.measured.contains("×1.30"), "{}", pooled_off.measured);
        assert_eq!(event_rate("exits", Some(0.4), None, &[]).met, None);
        assert_eq!(event_rate("exits", None, Some(0.4), &[]).met, None);
    }

    #[test]
    fn rates_heading_one_step_and_setup_against_their_bars() {
        assert_eq!(
            rate_ratio("collision rate", Some(0.0134), Some(0.0167)).met,
            Some(true)
        );
        assert_eq!(
            rate_ratio("collision rate", Some(0.0134), Some(0.0168)).met,
            Some(false)
        );
        assert_eq!(rate_ratio("off-road rate", None, Some(0.3)).met, None);
        assert_eq!(heading_motion(Some(0.18), Some(5.18)).met, Some(true));
        assert_eq!(heading_motion(Some(0.18), Some(5.19)).met, Some(false));
        assert_eq!(one_step(Some((0.0943, 0.0970))).met, Some(true));
        assert_eq!(one_step(Some((0.0973, 0.0970))).met, Some(false));
        assert_eq!(one_step(None).met, None);
        assert_eq!(setup(64, 30.0, false).met, Some(true));
        assert_eq!(setup(63, 30.0, false).met, Some(false));
        assert_eq!(setup(64, 15.0, false).met, Some(false));
        assert_eq!(setup(64, 30.0, true).met, Some(false));
    }

    #[test]
    fn the_map_target_needs_every_layer() {
        let layers = vec!["lane".to_string(), "stop line".to_string()];
        let all = map_iou(&layers, &[Some(0.85), Some(0.81)], &[Some(0.9), Some(0.9)], 30);
        assert_eq!(all.met, Some(true), "{all:?}");
        let one = map_iou(&layers, &[Some(0.85), Some(0.79)], &[Some(0.9), Some(0.3)], 30);
        assert_eq!(one.met, Some(false));
        assert!(
            one.measured.contains("stop line 0.79 (context 0.30)"),
            "{}",
            one.measured
        );
        let missing = map_iou(&layers, &[Some(0.85), None], &[], 30);
        assert_eq!(missing.met, Some(false));
        assert_eq!(map_iou(&layers, &[None, None], &[], 30).met, None);
    }
}
