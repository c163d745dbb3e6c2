//! `umgen tokenize`: every frame of a dataset through every modality, into a token cache.

use crate::error::{Result, UmgenError};
use std::path::Path;
use umgen_data::{Dataset, TokenClip, TokenIndex};
use umgen_modality::ModalityRegistry;

/// What a tokenize run did.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct TokenizeReport {
    /// Shards written.
    pub written: usize,
    /// Shards already present and skipped.
    pub skipped: usize,
    /// Frames tokenized.
    pub frames: usize,
}

/// Tokenizes the clips of `split` (all when `None`) into `out`, one shard per log, using `threads`
/// threads (clips in parallel). Thread k uses `registries[k % len]`: one registry per device spreads the
/// tokenizers' work over several GPUs; every registry must hold the same modalities (the first one's
/// layout names the cache). Shards the index already lists for this layout are skipped; a cache made
/// for another layout is refused. `progress(done, total)` counts clips.
pub fn tokenize_dataset(
    registries: &[ModalityRegistry],
    data: &Dataset,
    out: &Path,
    split: Option<&str>,
    threads: usize,
    mut progress: impl FnMut(usize, usize) + Send,
) -> Result<TokenizeReport> {
    let fail = |message: String| {
        UmgenError::Data(umgen_data::DataError::Request {
            path: out.into(),
            message,
        })
    };
    let Some(registry) = registries.first() else {
        return Err(fail("no modality registry to tokenize with".into()));
    };
    let layout = registry.layout()?;
    for other in &registries[1..] {
        if other.layout()?.fingerprint() != layout.fingerprint() {
            return Err(fail(
                "the registries of the devices differ in their layouts".into(),
            ));
        }
    }
    let mut index = match TokenIndex::load(out)? {
        Some(i) if i.fingerprint != layout.fingerprint() => {
            return Err(fail(
                "holds tokens of another layout; choose a new output directory".into(),
            ));
        }
        Some(i) => i,
        None => TokenIndex::new(layout.fingerprint(), layout.len(), data.index().frame_interval),
    };
    std::fs::create_dir_all(out).map_err(|e| fail(e.to_string()))?;
    let wanted = |c: &umgen_data::ClipEntry| split.is_none_or(|s| s == c.split);
    let total = data.clips().iter().filter(|c| wanted(c)).count();
    let (mut report, mut done) = (TokenizeReport::default(), 0);
    for log in &data.index().logs {
        let clips: Vec<usize> = (0..data.clips().len())
            .filter(|&i| data.clips()[i].log == log.id && wanted(&data.clips()[i]))
            .collect();
        if clips.is_empty() {
            continue;
        }
        if shard_done(&index, out, &log.id, clips.len()) {
            report.skipped += 1;
            done += clips.len();
            progress(done, total);
            continue;
        }
        let per_clip = tokenize_clips(registries, data, &clips, threads, |n| progress(done + n, total))?;
        let (mut rows, mut entries) = (Vec::new(), Vec::new());
        for (&c, clip_rows) in clips.iter().zip(per_clip) {
            let e = &data.clips()[c];
            entries.push(TokenClip {
                id: e.id.clone(),
                split: e.split.clone(),
                start: rows.len(),
                frames: clip_rows.len(),
            });
            rows.extend(clip_rows);
        }
        report.frames += rows.len();
        index.add_shard(out, &log.id, entries, &rows)?;
        report.written += 1;
        done += clips.len();
        progress(done, total);
    }
    // Each device's modalities counted their own clamps; the log gives the sums.
    let mut clamped: std::collections::BTreeMap<(String, String), (u64, u64)> = Default::default();
    for m in registries.iter().flat_map(|r| r.modalities()) {
        for c in m.clamp_report() {
            let e = clamped
                .entry((m.spec().name.clone(), c.field.clone()))
                .or_default();
            (e.0, e.1) = (e.0 + c.below, e.1 + c.above);
        }
    }
    for ((modality, field), (below, above)) in clamped.into_iter().filter(|(_, (b, a))| b + a > 0) {
        tracing::warn!("{modality}: `{field}` clamped {below} values below and {above} above its range");
    }
    Ok(report)
}

/// The token rows of one clip, tagged with its position in the work list.
type ClipRows = (usize, Vec<Vec<u32>>);

/// Rows of each clip, clips spread over threads (thread k on `registries[k % len]`).
fn tokenize_clips(
    registries: &[ModalityRegistry],
    data: &Dataset,
    clips: &[usize],
    threads: usize,
    progress: impl FnMut(usize) + Send,
) -> Result<Vec<Vec<Vec<u32>>>> {
    let next = std::sync::atomic::AtomicUsize::new(0);
    let finished = std::sync::atomic::AtomicUsize::new(0);
    let progress = std::sync::Mutex::new(progress);
    let results: Vec<Result<Vec<ClipRows>>> = std::thread::scope(|s| {
        let workers: Vec<_> = (0..threads.clamp(1, clips.len().max(1)))
            .map(|w| {
                let registry = &registries[w % registries.len()];
                let (next, finished, progress) = (&next, &finished, &progress);
                s.spawn(move || {
                    let mut mine = Vec::new();
                    loop {
                        let k = next.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
                        let Some(&c) = clips.get(k) else { return Ok(mine) };
                        let clip = data.read_clip(c)?;
                        mine.push((k, registry.tokenize_clip(&clip)?));
                        let n = finished.fetch_add(1, std::sync::atomic::Ordering::Relaxed) + 1;
                        if let Ok(mut p) = progress.lock() {
                            p(n);
                        }
                    }
                })
            })
            .collect();
        workers
            .into_iter()
            .map(|w| {
                w.join()
                    .unwrap_or_else(|_| Err(UmgenError::Text("a tokenizing thread panicked".into())))
            })
            .collect()
    });
    let mut all: Vec<ClipRows> = Vec::new();
    for r in results {
        all.extend(r?);
    }
    all.sort_by_key(|(k, _)| *k);
    Ok(all.into_iter().map(|(_, rows)| rows).collect())
}

/// Whether the cache in `out` (with `index`) holds the shard of `log` with all its `clips`.
fn shard_done(index: &TokenIndex, out: &Path, log: &str, clips: usize) -> bool {
    index
        .shards
        .iter()
        .any(|s| s.log == log && s.clips.len() == clips)
        && out.join(format!("shards/{log}.tok")).exists()
}

/// How many logs of `data` (clips of `split`, or all) the token cache in `out` still lacks; what
/// [`tokenize_dataset`] would write. Ranks other than 0 poll this while rank 0 tokenizes.
pub fn tokens_missing(data: &Dataset, out: &Path, split: Option<&str>) -> Result<usize> {
    let index = TokenIndex::load(out)?;
    let wanted = |c: &umgen_data::ClipEntry| split.is_none_or(|s| s == c.split);
    Ok(data
        .index()
        .logs
        .iter()
        .filter(|log| {
            let clips = data
                .clips()
                .iter()
                .filter(|c| c.log == log.id && wanted(c))
                .count();
            clips > 0 && index.as_ref().is_none_or(|i| !shard_done(i, out, &log.id, clips))
        })
        .count())
}
