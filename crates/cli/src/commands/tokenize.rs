//! `umgen tokenize`: a dataset through every modality of a config into a token cache.

use crate::cli::TokenizeArgs;
use crate::device::Device;
use umgen::data::Dataset;
use umgen::{UmgenConfig, tokenize_dataset};

/// Tokenizes the dataset.
pub fn run(a: &TokenizeArgs, kinds: &crate::Kinds) -> anyhow::Result<()> {
    let config = UmgenConfig::load(&a.config.config, &a.config.set)?;
    let devices = a
        .device
        .split(',')
        .map(|d| Device::parse(d.trim()))
        .collect::<anyhow::Result<Vec<_>>>()?;
    let threads = a.threads.unwrap_or_else(|| default_threads(&devices));
    let registries = registries(&config, &devices, threads, kinds)?;
    let registry = &registries[0];
    let data = Dataset::open(&a.data)?;
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

/// The registries the tokenizing threads use (thread k takes number k modulo their count): one per GPU,
/// whose encodes queue on that device's tokenizers; on the CPU one per thread, since a thread's encode
/// holds its tokenizer's lock: with one registry for all, 16 threads encoded one at a time (48,171 frames
/// of `small-bundled` in 550 s on 16 cores, 400 s on 2).
pub fn registries(
    config: &UmgenConfig,
    devices: &[Device],
    threads: usize,
    kinds: &crate::Kinds,
) -> anyhow::Result<Vec<umgen::modality::ModalityRegistry>> {
    let cpu_only = devices.iter().all(|d| !matches!(d, Device::Cuda(_)));
    let copies = if cpu_only { threads.max(1) } else { devices.len() };
    devices
        .iter()
        .cycle()
        .take(copies)
        .map(|d| Ok(config.registry(&kinds.catalog_with(d.codec_loader())?)?))
        .collect()
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

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]
    use super::*;
    use std::path::PathBuf;

    #[test]
    fn cpu_threads_get_their_own_tokenizers() {
        let root = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../..");
        let set = ["map", "image"].map(|m| {
            format!(
                "modality.{m}.tokenizer={}",
                root.join(format!("data/tokenizers/tiny-{m}")).display()
            )
        });
        let config = UmgenConfig::load(&root.join("configs/tiny.toml"), &set).unwrap();
        let regs = registries(&config, &[Device::Cpu], 3, &Default::default()).unwrap();
        assert_eq!(regs.len(), 3);
        // No two threads share a modality (and with it a tokenizer's lock).
        for (i, a) in regs.iter().enumerate() {
            for b in &regs[i + 1..] {
                for (x, y) in a.modalities().iter().zip(b.modalities()) {
                    assert!(!std::sync::Arc::ptr_eq(x, y), "{}", x.spec().name);
                }
            }
        }
        assert_eq!(
            regs[0].layout().unwrap().fingerprint(),
            regs[2].layout().unwrap().fingerprint()
        );
        assert_eq!(
            registries(&config, &[Device::Cpu], 0, &Default::default())
                .unwrap()
                .len(),
            1
        );
    }
}
