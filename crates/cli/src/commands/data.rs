//! `umgen data sumo`, `umgen data info` and `umgen data kinematics`.

use crate::cli::{DataCommand, InfoArgs, KinematicsArgs, SumoArgs};
use std::io::Write;
use umgen_data::sumo::{ImportOptions, import};
use umgen_data::{Dataset, Summary};

/// Runs a data subcommand.
pub fn run(command: DataCommand) -> anyhow::Result<()> {
    match command {
        DataCommand::Sumo(args) => sumo(&args),
        DataCommand::Info(args) => info(&args),
        DataCommand::Kinematics(args) => kinematics(&args),
    }
}

fn sumo(a: &SumoArgs) -> anyhow::Result<()> {
    let mut o = ImportOptions::new(a.net.clone(), a.fcd.clone(), a.out.clone());
    o.types.clone_from(&a.types);
    o.name.clone_from(&a.name);
    o.network_name.clone_from(&a.network_name);
    o.split.clone_from(&a.split);
    (o.clip_frames, o.min_frames, o.ego_every) = (a.clip_frames, a.min_frames, a.ego_every);
    o.tls.clone_from(&a.tls);
    let spinner =
        indicatif::ProgressBar::new_spinner().with_message(format!("importing {}", a.fcd.display()));
    spinner.enable_steady_tick(std::time::Duration::from_millis(120));
    let report = import(&o);
    spinner.finish_and_clear();
    let r = report?;
    tracing::info!(
        "{}: log `{}` on network `{}`: {} steps, {} actors, {} clips, {} frames{}{}",
        a.out.display(),
        r.log,
        r.network,
        r.steps,
        r.tracks,
        r.clips,
        r.frames,
        if a.tls.is_some() {
            format!(", {} signal heads", r.signal_heads)
        } else {
            String::new()
        },
        if r.skipped > 0 {
            format!(" ({} records of unmodelled classes left out)", r.skipped)
        } else {
            String::new()
        }
    );
    Ok(())
}

fn info(a: &InfoArgs) -> anyhow::Result<()> {
    let ds = Dataset::open(&a.data)?;
    let idx = ds.index();
    let mut out = std::io::stdout().lock();
    writeln!(out, "dataset     {}", a.data.display())?;
    writeln!(out, "interval    {} s", idx.frame_interval)?;
    writeln!(
        out,
        "networks    {}",
        idx.networks
            .iter()
            .map(|n| n.id.as_str())
            .collect::<Vec<_>>()
            .join(", ")
    )?;
    for split in ["train", "val", "test"] {
        let clips: Vec<_> = idx.clips.iter().filter(|c| c.split == split).collect();
        if !clips.is_empty() {
            let frames: usize = clips.iter().map(|c| c.frames).sum();
            writeln!(out, "{split:<11} {} clips, {frames} frames", clips.len())?;
        }
    }
    writeln!(out, "logs")?;
    for l in &idx.logs {
        let signals = l
            .signals
            .as_ref()
            .map_or(String::new(), |s| format!("  {} signal heads", s.heads));
        writeln!(
            out,
            "  {:<16} {:<12} {:>6} steps {:>6} actors  {}{signals}",
            l.id, l.network, l.steps, l.tracks, l.split
        )?;
    }
    let row = |out: &mut dyn Write, name: &str, s: &Summary| {
        writeln!(
            out,
            "  {name:<12} {:>10.3} {:>10.3} {:>10.3} {:>10.3}",
            s.min,
            s.max,
            s.mean(),
            s.std()
        )
    };
    writeln!(
        out,
        "statistics over {} frames          min        max       mean        std",
        idx.stats.frames
    )?;
    for (group, map) in [("ego", &idx.stats.ego), ("agent", &idx.stats.agent)] {
        writeln!(out, "{group}")?;
        for (k, s) in map {
            row(&mut out, k, s)?;
        }
    }
    let cats: Vec<String> = idx
        .stats
        .categories
        .iter()
        .map(|(k, v)| format!("{k} {v}"))
        .collect();
    writeln!(out, "categories  {}", cats.join(", "))?;
    Ok(())
}

fn kinematics(a: &KinematicsArgs) -> anyhow::Result<()> {
    use umgen_eval::kinematics::{Predictor, clip_errors, quantile};
    anyhow::ensure!(
        !a.horizons.is_empty() && a.horizons.iter().all(|&h| h > 0),
        "--horizons: frames ahead must be at least 1"
    );
    let category = match a.category.as_deref() {
        None => None,
        Some(name) => Some(umgen::scene::AgentCategory::from_name(name).ok_or_else(|| {
            anyhow::anyhow!("--category: unknown category `{name}` (vehicle, pedestrian or cyclist)")
        })?),
    };
    let ds = Dataset::open(&a.data)?;
    let clips: Vec<usize> = (0..ds.clips().len())
        .filter(|&i| ds.clips()[i].split == a.split)
        .collect();
    anyhow::ensure!(
        !clips.is_empty(),
        "{}: no clips in split `{}`",
        a.data.display(),
        a.split
    );
    let mut errors: Vec<[Vec<f64>; Predictor::ALL.len()]> = vec![Default::default(); a.horizons.len()];
    let bar = indicatif::ProgressBar::new(clips.len() as u64);
    for &i in &clips {
        let clip = ds.read_clip(i)?;
        for (e, &h) in errors.iter_mut().zip(&a.horizons) {
            for (all, one) in e.iter_mut().zip(clip_errors(&clip, h, category)) {
                all.extend(one);
            }
        }
        bar.inc(1);
    }
    bar.finish_and_clear();
    let dt = ds.index().frame_interval;
    let mut out = std::io::stdout().lock();
    writeln!(
        out,
        "{}: split `{}`, {} clips; {} position error (m) against the recorded states",
        a.data.display(),
        a.split,
        clips.len(),
        category.map_or("agent", |c| c.name())
    )?;
    writeln!(
        out,
        "{:>8} {:<22} {:>9} {:>8} {:>8} {:>8}",
        "ahead", "predictor", "agents", "mean", "median", "p90"
    )?;
    let f = |x: Option<f64>| x.map_or("-".to_string(), |x| format!("{x:.4}"));
    for (e, &h) in errors.iter().zip(&a.horizons) {
        for (v, p) in e.iter().zip(Predictor::ALL) {
            let mean = (!v.is_empty()).then(|| v.iter().sum::<f64>() / v.len() as f64);
            writeln!(
                out,
                "{:>7.1}s {:<22} {:>9} {:>8} {:>8} {:>8}",
                dt * h as f64,
                p.name(),
                v.len(),
                f(mean),
                f(quantile(v, 0.5)),
                f(quantile(v, 0.9))
            )?;
        }
    }
    Ok(())
}
