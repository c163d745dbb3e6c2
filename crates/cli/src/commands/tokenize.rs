//! `umgen tokenize`: a dataset through every modality of a config into a token cache.

use crate::cli::TokenizeArgs;
use crate::device::Device;
use umgen::data::Dataset;
use umgen::{UmgenConfig, builtin_catalog_with, tokenize_dataset};

/// Tokenizes the dataset.
pub fn run(a: &TokenizeArgs) -> anyhow::Result<()> {
    let config = UmgenConfig::load(&a.config.config, &a.config.set)?;
    let devices = a
        .device
        .split(',')
        .map(|d| Device::parse(d.trim()))
        .collect::<anyhow::Result<Vec<_>>>()?;
    // One registry (tokenizers loaded once) per device.
    let registries = devices
        .iter()
        .map(|d| Ok(config.registry(&builtin_catalog_with(d.codec_loader())?)?))
        .collect::<anyhow::Result<Vec<_>>>()?;
    let registry = &registries[0];
    let data = Dataset::open(&a.data)?;
    let threads = a.threads.unwrap_or_else(|| default_threads(&devices));
    let started = std::time::Instant::now();
    let report = with_progress(&registries, &data, &a.out, a.split.as_deref(), threads)?;
    tracing::info!(
        "{}: {} shards written ({} frames), {} already there, in {:.1} s; layout {} (N = {})",
        a.out.display(),
        report.written,
        report.frames,
        report.skipped,
        started.elapsed().as_secs_f64(),
        &registry.layout()?.fingerprint()[..12],
        registry.layout()?.len()
    );
    Ok(())
}

/// Tokenizing threads unless told: one per core on the CPU, at most 2 per GPU. Each thread encodes on its
/// own device stream with its own memory pool: 16 threads per H200 (64 cores, 4 GPUs) ran out of device
/// memory; 2 per GPU tokenized 388 frames/s on 4 H200s.
pub fn default_threads(devices: &[Device]) -> usize {
    let cores = std::thread::available_parallelism().map_or(1, |n| n.get());
    let gpus = devices.iter().filter(|d| matches!(d, Device::Cuda(_))).count();
    if gpus > 0 { cores.min(2 * gpus) } else { cores }
}

/// [`tokenize_dataset`] under a progress bar of clips.
pub fn with_progress(
    registries: &[umgen::modality::ModalityRegistry],
    data: &Dataset,
    out: &std::path::Path,
    split: Option<&str>,
    threads: usize,
) -> anyhow::Result<umgen::TokenizeReport> {
    let bar = crate::progress::bar(0, "clips tokenized")?;
    let report = tokenize_dataset(registries, data, out, split, threads, |done, total| {
        bar.set_length(total as u64);
        bar.set_position(done as u64);
    })?;
    bar.finish_and_clear();
    Ok(report)
}
