//! The Markdown page of `umgen eval` (`report.md`), written from its `report.json` values.

use std::fmt::Write as _;
use std::path::Path;
use umgen_eval::mmd::Group;

/// A value to four decimals, `-` where the report has none.
fn num(v: &serde_json::Value) -> String {
    v.as_f64().map_or("-".to_string(), |x| format!("{x:.4}"))
}

/// `report.md`: the measures table, the L2 over the horizon, the agents against the constant-velocity
/// baseline rounded to the agent bins (what a token model that moved every agent at its last velocity
/// would score), against constant acceleration, as is and rounded, and against constant acceleration
/// from the unbinned state.
pub fn markdown(generated: &Path, report: &serde_json::Value, real_frames: usize) -> anyhow::Result<String> {
    let mut md = String::new();
    writeln!(md, "# Evaluation of {}\n", generated.display())?;
    writeln!(md, "| measure | value |\n|---|---|")?;
    if let Some(n) = report["contexts"].as_u64() {
        writeln!(md, "| contexts (clips continued) | {n} |")?;
    }
    if report["recorded_ego"].as_bool().unwrap_or(false) {
        writeln!(
            md,
            "| ego actions | recorded (`--recorded-ego`): ego L2 is the bins' rounding |"
        )?;
    }
    let rates = &report["collision_rate"];
    writeln!(md, "| collision rate, generated | {} |", num(&rates["generated"]))?;
    writeln!(
        md,
        "| collision rate, real ({real_frames} frames) | {} |",
        num(&rates["real"])
    )?;
    for g in Group::ALL {
        writeln!(md, "| MMD {} | {} |", g.name(), num(&report["mmd"][g.name()]))?;
    }
    super::eval_targets::targets_markdown(&mut md, &report["targets"])?;
    horizon_markdown(&mut md, &report["horizon"])?;
    events_markdown(&mut md, &report["horizon"])?;
    map_markdown(&mut md, &report["map"])?;
    let rows = report["l2"].as_array().map_or(&[][..], |r| &r[..]);
    if rows.is_empty() {
        return Ok(md);
    }
    let cells = |r: &serde_json::Value, keys: &[&str]| {
        let seconds = r["seconds"].as_f64().unwrap_or(0.0);
        let values: Vec<String> = keys.iter().map(|k| num(&r[*k])).collect();
        format!("| {seconds:.1} | {} |", values.join(" | "))
    };
    writeln!(
        md,
        "\n| horizon (s) | ego L2 model | ego L2 const. vel. | agents L2 model | agents L2 const. vel. \
         | agents median model | agents median const. vel. | agents p90 model | agents p90 const. vel. |\n\
         |---|---|---|---|---|---|---|---|---|"
    )?;
    for r in rows {
        let keys = [
            "ego_model",
            "ego_constant_velocity",
            "agents_model",
            "agents_constant_velocity",
            "agents_model_median",
            "agents_constant_velocity_median",
            "agents_model_p90",
            "agents_constant_velocity_p90",
        ];
        writeln!(md, "{}", cells(r, &keys))?;
    }
    agents_table(
        &mut md,
        rows,
        "Agents against constant velocity rounded to the agent bins of the real next ego frame (the \
         baseline as a token model could output it):",
        &[
            ("model", "model"),
            ("constant_velocity_binned", "binned const. vel."),
        ],
    )?;
    agents_table(
        &mut md,
        rows,
        "Agents against constant acceleration (each agent's velocity change over the last context frame \
         kept; the prediction `backbone.track_accel` hints the model with), as is and rounded to the agent \
         bins:",
        &[
            ("model", "model"),
            ("constant_acceleration", "const. acc."),
            ("constant_acceleration_binned", "binned const. acc."),
        ],
    )?;
    agents_table(
        &mut md,
        rows,
        "Agents against constant acceleration from the recorded, unbinned state of the last two context \
         frames (what the tokens round away given back: as well as extrapolating the present can do; the \
         rest of the motion is velocity change):",
        &[
            ("model", "model"),
            ("real_state_constant_acceleration", "real-state const. acc."),
            (
                "real_state_constant_acceleration_binned",
                "binned real-state const. acc.",
            ),
        ],
    )?;
    hint_markdown(&mut md, rows)?;
    Ok(md)
}

/// One step ahead with the recorded ego: the agents the model kept on its hint's bins and those it moved
/// off them (`hint` of the first row, when `eval` measured it).
fn hint_markdown(md: &mut String, rows: &[serde_json::Value]) -> std::fmt::Result {
    let Some(h) = rows.first().map(|r| &r["hint"]).filter(|h| h.is_object()) else {
        return Ok(());
    };
    writeln!(
        md,
        "\nOne step ahead, the model against its hint (the binned constant-acceleration prediction above, \
         which `backbone.track_accel` gives the model): the agents it placed on the hint's bins and those it \
         moved off them, with their mean errors over agents (m) and, for the moved ones, the hint's error and \
         whether moving brought them closer to the truth; the last column is the mean error had the model \
         copied the hint for every agent.\n\n\
         | agents | on the hint | error there | moved off | error | the hint's error | closer | farther | \
         copying the hint everywhere |\n|---|---|---|---|---|---|---|---|---|"
    )?;
    let keys = [
        "followed",
        "followed_error",
        "departed",
        "departed_error",
        "departed_hint_error",
        "closer",
        "farther",
        "hint_error",
    ];
    let values: Vec<String> = keys.iter().map(|k| num(&h[*k])).collect();
    writeln!(md, "| {} | {} |", h["agents"], values.join(" | "))
}

/// A table of the agents' mean, median and 90th percentile over the horizon for each predictor
/// (`agents_<key>`, `_median`, `_p90` of each row; `label` in the header), after `intro`.
fn agents_table(
    md: &mut String,
    rows: &[serde_json::Value],
    intro: &str,
    predictors: &[(&str, &str)],
) -> anyhow::Result<()> {
    let stats = [("", "mean"), ("_median", "median"), ("_p90", "p90")];
    let header: Vec<String> = stats
        .iter()
        .flat_map(|(_, stat)| predictors.iter().map(move |(_, label)| format!("{label} {stat}")))
        .collect();
    writeln!(
        md,
        "\n{intro}\n\n| horizon (s) | {} |\n|---|{}",
        header.join(" | "),
        "---|".repeat(header.len())
    )?;
    for r in rows {
        let seconds = r["seconds"].as_f64().unwrap_or(0.0);
        let values: Vec<String> = stats
            .iter()
            .flat_map(|(suffix, _)| {
                predictors
                    .iter()
                    .map(move |(key, _)| num(&r[format!("agents_{key}{suffix}")]))
            })
            .collect();
        writeln!(md, "| {seconds:.1} | {} |", values.join(" | "))?;
    }
    Ok(())
}

/// The horizon table of `report.md`: the real split's statistics, then each second's of the rollouts.
pub fn horizon_markdown(md: &mut String, horizon: &serde_json::Value) -> std::fmt::Result {
    let Some(rows) = horizon["seconds"].as_array().filter(|r| !r.is_empty()) else {
        return Ok(());
    };
    writeln!(
        md,
        "\n## Over the horizon\n\nPer second generated, and over the whole horizon (every generated frame pooled: \
         the last row), against the real split over every frame of its clips (agents as the slots hold them). Collision: fraction of agents overlapping another; overlapping ego: fraction of frames in which an agent overlaps the ego's box (5.176 × 2.297 m, the new-agent rule's); onsets: collisions \
         begun per second (pairs overlapping that did not a frame before), and the share of them driven at speed \
         into a standing agent (one below 1 m/s, the other above 5 m/s before); approaches: agents above 5 m/s \
         with a standing agent less than 3 s ahead in their lane, per second, and the share that braked by 1 m/s² \
         or more by the next frame (braking begun: the same share of the approaches whose agent had not braked over the step before); starts: of the agents standing (below 1 m/s) in a frame, the share moving in the next, \
         per second; off-road: fraction \
         of agent centres off the lanes, connectors and intersections (vehicles: of vehicle centres; ego on road: of the vehicle centres of frames whose ego is on the road, what the vehicles leave themselves; entering: of vehicles in the frame they entered; ego: fraction of frames whose ego is); heading–motion: median angle between \
         heading and velocity of agents above 1 m/s; speed (m/s), acceleration (m/s²) and the speed of \
         entering agents in the frame they entered as median (90th percentile).\n"
    )?;
    writeln!(
        md,
        "| second | frames | agents/frame | entries/s | exits/s | collision | overlapping ego | onsets/s | onsets at speed into standing | approaches/s | braking on approach | braking begun | starts/s | off-road | vehicles off-road | vehicles off-road, ego on road | entering off-road | ego off-road | heading–motion ° | speed | acceleration | entering speed | MMD {} |",
        Group::ALL.map(|g| g.name()).join(" / ")
    )?;
    writeln!(
        md,
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|"
    )?;
    let spread = |v: &serde_json::Value| match (v["p50"].as_f64(), v["p90"].as_f64()) {
        (Some(a), Some(b)) => format!("{a:.2} ({b:.2})"),
        _ => "-".into(),
    };
    let line = |md: &mut String, label: String, s: &serde_json::Value, mmd: Option<&serde_json::Value>| {
        let mmd = mmd.map_or("-".to_string(), |m| {
            Group::ALL.map(|g| num(&m[g.name()])).join(" / ")
        });
        writeln!(
            md,
            "| {label} | {} | {} | {} | {} | {} | {} | {} | {} | {} | {} | {} | {} | {} | {} | {} | {} | {} | {} | {} | {} | {} | {mmd} |",
            s["frames"],
            num(&s["agents_mean"]),
            num(&s["entries_per_s"]),
            num(&s["exits_per_s"]),
            num(&s["collision_rate"]),
            num(&s["ego_overlap_rate"]),
            num(&s["collision_onsets_per_s"]),
            num(&s["onsets_into_standing"]),
            num(&s["approaches_per_s"]),
            num(&s["approach_braking"]),
            num(&s["approach_braking_onset"]),
            num(&s["starts_per_standing_s"]),
            num(&s["off_road_rate"]),
            num(&s["vehicle_off_road_rate"]),
            num(&s["vehicle_off_road_ego_on_rate"]),
            num(&s["entering_off_road_rate"]),
            num(&s["ego_off_road_rate"]),
            num(&s["heading_motion_median_deg"]),
            spread(&s["speed"]),
            spread(&s["acceleration"]),
            spread(&s["entry_speed"]),
        )
    };
    line(md, "real".into(), &horizon["real"], None)?;
    for r in rows {
        line(md, r["second"].to_string(), &r["generated"], Some(&r["mmd"]))?;
    }
    let whole = &horizon["whole"];
    if whole.is_object() {
        line(
            md,
            format!("1–{}", rows.len()),
            &whole["generated"],
            Some(&whole["mmd"]),
        )?;
    }
    Ok(())
}

/// The events table of `report.md`: per second generated (and pooled), the agents entering and leaving
/// and the collisions begun, each count with its rate and the rate's 95 % interval (`EventCounts`).
pub fn events_markdown(md: &mut String, horizon: &serde_json::Value) -> std::fmt::Result {
    let Some(rows) = horizon["seconds"].as_array().filter(|r| !r.is_empty()) else {
        return Ok(());
    };
    writeln!(
        md,
        "\n## Events per second, with 95 % intervals\n\nAgents entering, agents leaving and collisions begun, \
         counted over the seconds of transitions between frames, with the rate per second and its 95 % \
         interval in brackets (the count taken as Poisson: exact up to 100 events, Byar's approximation \
         beyond). Events of one scene are not independent, so the uncertainty is if anything wider. A \
         second's rate is off the real one only where the real rate (or the band a target puts around it) \
         lies outside the interval. Inside: the share of the entries (exits) whose position a step before \
         (after), at their velocity, lies in the agents' range of the frame before (after): agents that \
         appear or vanish where they could have been seen, not across the range's edge. Leaving the road: \
         vehicles on the drivable area in a frame and off it in the next, the share of them moving (above \
         1 m/s) and, over the moving ones, the median of the largest turn of their heading over the 4 frames \
         before (near 0: driven straight off the road).\n"
    )?;
    writeln!(
        md,
        "| second | seconds counted | entries | entries/s | entries inside | exits | exits/s | exits inside | onsets | onsets/s | leaving the road | leaving/s | of them moving | their turn ° |\n|---|---|---|---|---|---|---|---|---|---|---|---|---|---|"
    )?;
    let share = |c: &serde_json::Value, k: &str, of: &str| match (c[k].as_u64(), c[of].as_u64()) {
        (Some(n), Some(all)) if all > 0 => format!("{:.2}", n as f64 / all as f64),
        _ => "-".to_string(),
    };
    let rate = |c: &serde_json::Value, k: &str, ci: &str| {
        let n = c[k].as_u64();
        let seconds = c["seconds"].as_f64().filter(|s| *s > 0.0);
        match (n, seconds, c[ci][0].as_f64(), c[ci][1].as_f64()) {
            (Some(n), Some(t), Some(lo), Some(hi)) => {
                format!("{n} | {:.3} [{lo:.3}, {hi:.3}]", n as f64 / t)
            }
            _ => "- | -".to_string(),
        }
    };
    let line = |md: &mut String, label: String, s: &serde_json::Value| {
        let c = &s["counts"];
        let mut leaving = c["leaving_road"].clone();
        leaving["seconds"] = c["seconds"].clone();
        writeln!(
            md,
            "| {label} | {} | {} | {} | {} | {} | {} | {} | {} | {} |",
            c["seconds"].as_f64().map_or("-".into(), |t| format!("{t:.1}")),
            rate(c, "entries", "entries_per_s_95"),
            share(c, "entries_inside", "entries"),
            rate(c, "exits", "exits_per_s_95"),
            share(c, "exits_inside", "exits"),
            rate(c, "onsets", "onsets_per_s_95"),
            rate(&leaving, "vehicles", "per_s_95"),
            share(&leaving, "moving", "vehicles"),
            num(&leaving["turn_median_deg"]),
        )
    };
    line(md, "real".into(), &horizon["real"])?;
    for r in rows {
        line(md, r["second"].to_string(), &r["generated"])?;
    }
    if horizon["whole"].is_object() {
        line(md, format!("1–{}", rows.len()), &horizon["whole"]["generated"])?;
    }
    Ok(())
}

/// The map table of `report.md`: each layer's IoU of the decoded map codes with the map rendered at the
/// ego pose, for the context frames (real codes, real poses) and each second generated.
pub fn map_markdown(md: &mut String, map: &serde_json::Value) -> std::fmt::Result {
    let (Some(layers), Some(rows)) = (map["layers"].as_array(), map["seconds"].as_array()) else {
        return Ok(());
    };
    writeln!(
        md,
        "\n## Map at the generated pose\n\nPer layer, the IoU of the map decoded from the map codes with the map \
         rendered from the context clip's road network at the frame's ego pose, cells pooled over the frames, with \
         the F1 within one pixel in brackets. The context frames hold real codes at real poses: what the \
         tokenizer keeps. Off the map: the fraction of vehicles whose centre falls on a cell of the map their \
         own frame's codes decode to that no lane, intersection or lane connector covers, of all and of \
         those entering; and of the vehicles off it, the share that was off it in the frame it entered.\n"
    )?;
    let names: Vec<&str> = layers.iter().filter_map(|l| l.as_str()).collect();
    writeln!(
        md,
        "| second | frames | {} | vehicles off the map | entering off it | of those off, entered off |",
        names.join(" | ")
    )?;
    writeln!(md, "|---|---|{}---|---|---|", "---|".repeat(names.len()))?;
    let line = |md: &mut String, label: String, r: &serde_json::Value| {
        let ious: Vec<String> = (0..names.len())
            .map(|i| match r["f1_within_1px"][i].as_f64() {
                Some(f1) => format!("{} ({f1:.3})", num(&r["iou"][i])),
                None => num(&r["iou"][i]),
            })
            .collect();
        writeln!(
            md,
            "| {label} | {} | {} | {} | {} | {} |",
            r["frames"],
            ious.join(" | "),
            num(&r["vehicles_off_map"]),
            num(&r["entering_off_map"]),
            num(&r["off_map_entered_off"])
        )
    };
    line(md, "context".into(), &map["context"])?;
    for r in rows {
        line(md, r["second"].to_string(), r)?;
    }
    writeln!(
        md,
        "\nWithin the context's view: of each frame's window, the cells some context frame's window showed (the \
         real road network was in the model's input there; beyond them the generated ego has driven into ground \
         the context never showed, and the model's roads are its own). The share of the windows' cells they are, \
         each layer's IoU over them, and the vehicles whose centre lies there, with the share of them on no \
         drivable cell of the real network's map; of the vehicles entering a frame, the share that enter \
         within the view, and of those the share off the real road.\n"
    )?;
    writeln!(
        md,
        "| second | share of the window | {} | vehicles | off the road | entering within it | of those off the road |",
        names.join(" | ")
    )?;
    writeln!(md, "|---|---|{}---|---|---|---|", "---|".repeat(names.len()))?;
    let seen = |md: &mut String, label: String, r: &serde_json::Value| {
        let v = &r["context_view"];
        let ious: Vec<String> = (0..names.len()).map(|i| num(&v["iou"][i])).collect();
        writeln!(
            md,
            "| {label} | {} | {} | {} | {} | {} | {} |",
            num(&v["share"]),
            ious.join(" | "),
            v["vehicles"],
            num(&v["vehicles_off_road"]),
            num(&v["entering_inside"]),
            num(&v["entering_off_road"])
        )
    };
    seen(md, "context".into(), &map["context"])?;
    for r in rows {
        seen(md, r["second"].to_string(), r)?;
    }
    Ok(())
}
