//! `umgen data sumo` and `umgen data info`.

use crate::cli::{DataCommand, InfoArgs, SumoArgs};
use std::io::Write;
use umgen_data::sumo::{ImportOptions, import};
use umgen_data::{Dataset, Summary};

/// Runs a data subcommand.
pub fn run(command: DataCommand) -> anyhow::Result<()> {
    match command {
        DataCommand::Sumo(args) => sumo(&args),
        DataCommand::Info(args) => info(&args),
    }
}

fn sumo(a: &SumoArgs) -> anyhow::Result<()> {
    let mut o = ImportOptions::new(a.net.clone(), a.fcd.clone(), a.out.clone());
    o.types.clone_from(&a.types);
    o.name.clone_from(&a.name);
    o.network_name.clone_from(&a.network_name);
    o.split.clone_from(&a.split);
    (o.clip_frames, o.min_frames, o.ego_every) = (a.clip_frames, a.min_frames, a.ego_every);
    let spinner =
        indicatif::ProgressBar::new_spinner().with_message(format!("importing {}", a.fcd.display()));
    spinner.enable_steady_tick(std::time::Duration::from_millis(120));
    let report = import(&o);
    spinner.finish_and_clear();
    let r = report?;
    tracing::info!(
        "{}: log `{}` on network `{}`: {} steps, {} actors, {} clips, {} frames{}",
        a.out.display(),
        r.log,
        r.network,
        r.steps,
        r.tracks,
        r.clips,
        r.frames,
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
        writeln!(
            out,
            "  {:<16} {:<12} {:>6} steps {:>6} actors  {}",
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
