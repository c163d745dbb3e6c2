//! `umgen bench …`: speed measurements.

use crate::cli::{BenchCommand, BenchDataArgs, BenchModelArgs};
use anyhow::Context;
use std::io::Write;
use std::path::PathBuf;
use std::time::Instant;
use umgen_data::Dataset;
use umgen_render::{Camera, MapView};

/// Runs a benchmark.
pub fn run(command: BenchCommand, kinds: &crate::Kinds) -> anyhow::Result<()> {
    match command {
        BenchCommand::Data(args) => data(&args),
        BenchCommand::Train(args) => super::bench_train::run(&args, kinds),
        BenchCommand::Allreduce(args) => super::bench_allreduce::allreduce(&args),
        BenchCommand::Generate(args) => super::bench_generate::run(&args, kinds),
    }
}

/// The config a benchmark measures: `config`, or `configs/<preset>.toml`, with the preset's overrides and
/// then `set`; tokenizers need not exist (speed does not depend on them). Also the file read and every
/// override applied.
pub fn bench_config(model: &BenchModelArgs) -> anyhow::Result<(umgen::UmgenConfig, PathBuf, Vec<String>)> {
    let (config, preset, set) = (model.config.as_deref(), model.preset, &model.set);
    let path = match (config, preset) {
        (Some(p), _) => p.to_path_buf(),
        (None, Some(p)) => PathBuf::from(format!("configs/{}.toml", p.name())),
        (None, None) => anyhow::bail!("give --config or --preset"),
    };
    let mut sets = preset.map(|p| p.overrides()).unwrap_or_default();
    sets.extend(set.iter().cloned());
    let loaded = umgen::UmgenConfig::load(&path, &sets).with_context(|| match preset {
        Some(p) if config.is_none() => format!(
            "preset `{}` reads {} (run from the repository root, or pass --config)",
            p.name(),
            path.display()
        ),
        _ => format!("loading {}", path.display()),
    })?;
    Ok((loaded.without_missing_tokenizers().0, path, sets))
}

/// Reads windows round-robin over every window of the dataset for a fixed time, single-threaded.
fn data(a: &BenchDataArgs) -> anyhow::Result<()> {
    let ds = Dataset::open(&a.data)?;
    let windows = ds.windows(a.frames, a.gap, None);
    anyhow::ensure!(
        !windows.is_empty(),
        "no clip holds a window of {} frames at gap {}",
        a.frames,
        a.gap
    );
    // A fixed stride through the windows visits clips in a scattered order, as a shuffled sampler does.
    let stride = (windows.len() / 7).max(1) | 1;
    let (view, camera) = (MapView::default(), Camera::default());
    let mut out = std::io::stdout().lock();
    writeln!(
        out,
        "dataset {} ({} windows of {} frames, gap {})",
        a.data.display(),
        windows.len(),
        a.frames,
        a.gap
    )?;
    let mut measure = |name: &str, map: bool, cam: bool| -> anyhow::Result<()> {
        let (start, mut n, mut agents) = (Instant::now(), 0usize, 0usize);
        while start.elapsed().as_secs_f64() < a.seconds {
            let w = windows[(n * stride) % windows.len()];
            let clip = ds.read_window(w.clip, w.start, a.frames, a.gap)?;
            agents += clip.frames.iter().map(|f| f.agents.len()).sum::<usize>();
            if map || cam {
                let net = clip
                    .network
                    .clone()
                    .ok_or_else(|| anyhow::anyhow!("clip without network"))?;
                for f in &clip.frames {
                    let pose = f.ego.pose2();
                    if map {
                        std::hint::black_box(view.render(&net, &pose));
                    }
                    if cam {
                        std::hint::black_box(camera.render(&net, &pose, &f.agents));
                    }
                }
            }
            n += 1;
        }
        let secs = start.elapsed().as_secs_f64();
        writeln!(
            out,
            "{name:<32} {:>10.1} windows/s {:>10.1} frames/s  ({n} windows, {:.1} agents/frame, 1 thread)",
            n as f64 / secs,
            (n * a.frames) as f64 / secs,
            agents as f64 / (n * a.frames).max(1) as f64
        )?;
        Ok(())
    };
    measure("states (poses, actions, agents)", false, false)?;
    if a.render {
        measure("states + map raster 6x256x256", true, false)?;
        measure("states + camera 256x512", false, true)?;
    }
    Ok(())
}
