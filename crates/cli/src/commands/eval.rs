//! `umgen eval`: the paper's measures on the output of `umgen generate` (docs/evaluation.md defines them).

use super::agents::AgentSlots;
use super::eval_truth::ground_truth;
use crate::cli::EvalArgs;
use anyhow::Context;
use umgen::data::Dataset;
use umgen::scene::{Agent, Frame};
use umgen_eval::collision::collision_rate;
use umgen_eval::hint::HintUse;
use umgen_eval::l2::{
    agent_errors, constant_acceleration_agents, constant_velocity_agents, ego_l2, median, on_grid, positions,
    quantile,
};
use umgen_eval::mmd::{Group, mmd};

/// Two positions on the same bins: both are bin centres of one grid, so they differ by rounding alone.
const SAME_BIN_M: f64 = 1e-6;

/// MMD per attribute group between two agent sets.
pub(super) fn mmd_groups(generated: &[&Agent], real: &[&Agent]) -> serde_json::Value {
    let mut out = serde_json::Map::new();
    for g in Group::ALL {
        let x: Vec<Vec<f64>> = generated.iter().map(|a| g.features(a)).collect();
        let y: Vec<Vec<f64>> = real.iter().map(|a| g.features(a)).collect();
        out.insert(g.name().into(), serde_json::json!(mmd(&x, &y)));
    }
    serde_json::Value::Object(out)
}

fn mean(v: &[f64]) -> Option<f64> {
    (!v.is_empty()).then(|| v.iter().sum::<f64>() / v.len() as f64)
}

/// One predictor's agent errors at a horizon: the mean of each scene (or context), and every matched
/// agent's error, for the median and 90th percentile.
#[derive(Default)]
struct AgentErrors {
    means: Vec<f64>,
    each: Vec<f64>,
}

impl AgentErrors {
    /// One scene's (or context's) errors.
    fn add(&mut self, errors: Vec<f64>) {
        self.means.extend(mean(&errors));
        self.each.extend(errors);
    }

    /// `agents_<name>` (mean of the means), `agents_<name>_median` and `agents_<name>_p90` into `row`.
    fn report(&self, name: &str, row: &mut serde_json::Value) {
        row[format!("agents_{name}")] = serde_json::json!(mean(&self.means));
        row[format!("agents_{name}_median")] = serde_json::json!(median(&self.each));
        row[format!("agents_{name}_p90")] = serde_json::json!(quantile(&self.each, 0.9));
    }
}

/// The errors of a generated frame's agents against the true global positions. With the recorded ego
/// (`recorded_ego`) the model's agent tokens are relative to the real ego pose `real`, which the frame's
/// decoded pose only approximates (the recorded actions rounded to their bins drift it by millimetres and
/// turn far agents by centimetres): they are placed from `real`, as the truth and the baselines are.
/// Otherwise the model drove its own ego, and its agents are placed from the pose it decoded.
fn model_agent_errors(
    f: &Frame,
    real: &umgen::scene::EgoPose,
    recorded_ego: bool,
    truth: &[(u64, [f64; 2])],
) -> Vec<f64> {
    let ego = if recorded_ego { real } else { &f.ego };
    agent_errors(&positions(ego, &f.agents), truth)
}

/// Evaluates.
pub fn run(a: &EvalArgs, kinds: &crate::Kinds) -> anyhow::Result<()> {
    let output = super::scenes::open_output(&a.generated, a.bundle.as_deref(), kinds)?;
    let scenes = super::scenes::generated_scenes(&a.generated, &output)?;
    let super::scenes::Output {
        meta,
        tokens,
        bundle,
        registry,
    } = output;
    // The agents' bins, for the baseline a token model could reach.
    let grid = AgentSlots::of(&bundle, &registry)?;
    let mut off_grid = 0usize;
    anyhow::ensure!(
        !scenes.is_empty(),
        "{}: no generated scenes",
        a.generated.display()
    );
    let ds = Dataset::open(&a.reference)?;
    let dt = meta["interval"].as_f64().unwrap_or(0.5);
    // `generate --recorded-ego`: the ego followed its recorded actions, so the ego L2 is only their
    // rounding to bins, and the agents' L2 is the model's given the real ego motion.
    let recorded_ego = meta["recorded_ego"].as_bool().unwrap_or(false);
    let mut report =
        serde_json::json!({"generated": a.generated, "reference": a.reference, "scenes": scenes.len()});

    // The real data's collision rate over a sample of the split (raw agents).
    // Read once: the horizon statistics take every frame of these clips too.
    let split_clips = (0..ds.clips().len())
        .filter(|&i| ds.clips()[i].split == a.split)
        .map(|i| ds.read_clip(i))
        .collect::<Result<Vec<_>, _>>()?;
    let mut real_frames: Vec<Vec<Agent>> = Vec::new();
    let mut initial: Vec<Agent> = Vec::new();
    for clip in &split_clips {
        initial.extend(clip.frames.first().map(|f| f.agents.clone()).unwrap_or_default());
        real_frames.extend(
            clip.frames
                .iter()
                .step_by(a.stride.max(1))
                .map(|f| f.agents.clone()),
        );
    }
    let generated_frames: Vec<&[Agent]> = scenes
        .iter()
        .flat_map(|s| s.frames.iter().map(|f| &f.agents[..]))
        .collect();
    report["collision_rate"] = serde_json::json!({
        "generated": collision_rate(generated_frames.iter().copied()),
        "real": collision_rate(real_frames.iter().map(|f| &f[..])),
        "real_frames": real_frames.len(),
    });

    let (mut l2_rows, mut mmd_rows) = (Vec::new(), Vec::new());
    let contexts = meta["contexts"].as_array().cloned().unwrap_or_default();
    if contexts.is_empty() {
        // Initial scenes (TrafficGen's setting): generated first frames against real first frames.
        let generated: Vec<&Agent> = scenes.iter().flat_map(|s| s.frames[0].agents.iter()).collect();
        let real: Vec<&Agent> = initial.iter().collect();
        mmd_rows.push(serde_json::json!({"frame": 1, "mmd": mmd_groups(&generated, &real)}));
    } else {
        let per = meta["scenes_per_context"].as_u64().unwrap_or(1) as usize;
        anyhow::ensure!(
            per >= 1 && scenes.len() == per * contexts.len(),
            "{}: {} scenes for {} contexts × {per}",
            a.generated.display(),
            scenes.len(),
            contexts.len()
        );
        let truths = contexts
            .iter()
            .map(|c| ground_truth(&ds, &registry, c, scenes[0].frames.len(), dt))
            .collect::<anyhow::Result<Vec<_>>>()?;
        let k = truths.iter().map(|t| t.poses.len()).min().unwrap_or(0);
        for h in 1..=k {
            let (mut model_ego, mut cv_ego) = (vec![], vec![]);
            // The model, then constant velocity and constant acceleration, each also rounded to the agent
            // bins of the real next ego frame.
            let mut model = AgentErrors::default();
            let [
                mut cv_errors,
                mut binned,
                mut ca_errors,
                mut ca_binned,
                mut real_ca,
                mut real_ca_binned,
            ] = std::array::from_fn::<AgentErrors, 6, _>(|_| AgentErrors::default());
            let (mut generated, mut real): (Vec<&Agent>, Vec<&Agent>) = (vec![], vec![]);
            let mut hint_use = HintUse::default();
            for (c, t) in truths.iter().enumerate() {
                let true_pos = positions(&t.poses[h - 1], &t.tracked[h - 1]);
                for s in &scenes[c * per..(c + 1) * per] {
                    let f = &s.frames[h - 1];
                    model_ego.push(ego_l2(&[f.ego], &[t.poses[h - 1]])[0]);
                    model.add(model_agent_errors(f, &t.poses[h - 1], recorded_ego, &true_pos));
                    generated.extend(f.agents.iter());
                }
                cv_ego.push(t.cv_ego[h - 1]);
                let cv = constant_velocity_agents(&t.last.ego, &t.last_agents, dt, h);
                let ca = match &t.before {
                    Some((ego, agents)) => {
                        constant_acceleration_agents(ego, agents, &t.last.ego, &t.last_agents, dt, h)
                    }
                    None => cv.clone(),
                };
                // The same from the recorded (unbinned) state: no rule that extrapolates the present alone
                // does much better, so the model's margin past it is what it learned of the scene.
                let [real_before, real_last] = &t.real_state;
                let before_ego = t.before.as_ref().map_or(&t.last.ego, |(e, _)| e);
                let ca_real =
                    constant_acceleration_agents(before_ego, real_before, &t.last.ego, real_last, dt, h);
                // The binned constant-acceleration prediction is the model's hint, on the bins it names
                // its agents in (the real next ego frame's).
                let mut hint = None;
                for (predicted, errors, on_bins, is_hint) in [
                    (&cv, &mut cv_errors, &mut binned, false),
                    (&ca, &mut ca_errors, &mut ca_binned, true),
                    (&ca_real, &mut real_ca, &mut real_ca_binned, false),
                ] {
                    errors.add(agent_errors(predicted, &true_pos));
                    if let Some(g) = &grid {
                        let on = on_grid(&t.poses[h - 1], predicted, |p| {
                            let (q, clamped) = g.round_xy(p);
                            off_grid += usize::from(clamped);
                            q
                        });
                        on_bins.add(agent_errors(&on, &true_pos));
                        if is_hint {
                            hint = Some(on);
                        }
                    }
                }
                if h == 1
                    && recorded_ego
                    && let Some(hint) = &hint
                {
                    for s in &scenes[c * per..(c + 1) * per] {
                        let placed = positions(&t.poses[0], &s.frames[0].agents);
                        hint_use.add(&HintUse::of(&placed, hint, &true_pos, SAME_BIN_M));
                    }
                }
                real.extend(t.agents[h - 1].iter());
            }
            let mut row = serde_json::json!({
                "horizon": h, "seconds": dt * h as f64,
                "ego_model": mean(&model_ego), "ego_constant_velocity": mean(&cv_ego),
            });
            model.report("model", &mut row);
            cv_errors.report("constant_velocity", &mut row);
            binned.report("constant_velocity_binned", &mut row);
            ca_errors.report("constant_acceleration", &mut row);
            ca_binned.report("constant_acceleration_binned", &mut row);
            real_ca.report("real_state_constant_acceleration", &mut row);
            real_ca_binned.report("real_state_constant_acceleration_binned", &mut row);
            if hint_use.agents > 0 {
                row["hint"] = serde_json::to_value(hint_use.summary())?;
            }
            l2_rows.push(row);
            mmd_rows.push(serde_json::json!({"frame": h, "mmd": mmd_groups(&generated, &real)}));
        }
        report["contexts"] = contexts.len().into();
        if off_grid > 0 {
            tracing::warn!(
                "{off_grid} constant-velocity or constant-acceleration predictions fell outside the agent \
                 bins' range; the binned baselines put them in the edge bin"
            );
        }
    }
    let per = meta["scenes_per_context"].as_u64().unwrap_or(1) as usize;
    let extent = umgen::agent_segment(&registry, &bundle.config)?.map(|(_, _, c)| [c.x, c.y]);
    let (horizon, rollout) =
        super::eval_horizon::horizon(&scenes, &contexts, per, &ds, &registry, split_clips, dt, extent)?;
    report["horizon"] = horizon;
    if let Some(view) = super::scenes::map_view(&bundle)? {
        let map =
            super::eval_map::map_consistency(&view, &registry, &tokens, &scenes, &contexts, per, &ds, dt)?;
        report["map"] = map.into();
    }
    report["recorded_ego"] = recorded_ego.into();
    let run = super::eval_targets::Run {
        contexts: contexts.len(),
        seconds: scenes.iter().map(|s| s.frames.len()).min().unwrap_or(0) as f64 * dt,
        recorded_ego,
    };
    let targets = super::eval_targets::targets(&run, rollout, &l2_rows, &report["map"]);
    report["targets"] = serde_json::to_value(&targets)?;
    let mut mmd_mean = serde_json::Map::new();
    for g in Group::ALL {
        let v: Vec<f64> = mmd_rows
            .iter()
            .filter_map(|r| r["mmd"][g.name()].as_f64())
            .collect();
        mmd_mean.insert(g.name().into(), serde_json::json!(mean(&v)));
    }
    report["l2"] = serde_json::json!(l2_rows);
    report["mmd_per_frame"] = serde_json::json!(mmd_rows);
    report["mmd"] = serde_json::Value::Object(mmd_mean);
    let out = a.out.clone().unwrap_or_else(|| a.generated.join("eval"));
    std::fs::create_dir_all(&out).with_context(|| format!("creating {}", out.display()))?;
    std::fs::write(out.join("report.json"), serde_json::to_vec_pretty(&report)?)?;
    if !l2_rows.is_empty() {
        super::eval_plot::l2_plot(&l2_rows, &out.join("l2.png"))?;
    }
    super::eval_plot::horizon_plot(&report["horizon"], &out.join("horizon.png"))?;
    let md = super::eval_report::markdown(&a.generated, &report, real_frames.len())?;
    std::fs::write(out.join("report.md"), &md)?;
    tracing::info!(
        "{}: report.json, report.md, horizon.png{}",
        out.display(),
        if l2_rows.is_empty() { "" } else { ", l2.png" }
    );
    Ok(())
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]
    use super::*;
    use crate::commands::eval_truth::tests::at;

    #[test]
    fn recorded_ego_places_the_model_agents_from_the_real_pose() {
        // The decoded ego drifted by 0.01 rad from the real pose; the model named the true agent (50 m
        // ahead). From the real pose it is exact; from the drifted one it is 50 · 0.01 = 0.5 m off.
        let real = umgen::scene::EgoPose {
            x: 3.0,
            y: 1.0,
            heading: 0.2,
            speed: 0.0,
        };
        let f = Frame {
            ego: umgen::scene::EgoPose {
                heading: 0.21,
                ..real
            },
            agents: vec![at(4, 50.0)],
            ..Frame::default()
        };
        let truth = positions(&real, &f.agents);
        assert_eq!(model_agent_errors(&f, &real, true, &truth), vec![0.0]);
        let own = model_agent_errors(&f, &real, false, &truth)[0];
        assert!((own - 0.5).abs() < 1e-3, "{own}");
    }
}
