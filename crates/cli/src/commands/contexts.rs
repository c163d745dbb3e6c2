//! The context clips `umgen generate` continues: `--context DATA:CLIP[:FRAMES]` and `--contexts
//! DATA:SPLIT:COUNT[:FRAMES]`, read from umgen datasets.

use crate::cli::GenerateArgs;
use anyhow::Context;
use std::path::Path;
use umgen::data::Dataset;
use umgen::scene::SceneClip;

/// A context: its frames, and the dataset and clip id for `meta.json`.
pub struct ContextClip {
    /// The context frames.
    pub clip: SceneClip,
    /// The dataset it was read from.
    pub data: String,
    /// Its clip id.
    pub id: String,
}

/// The contexts of `--context` and `--contexts` in batch order, and the frame interval; none from scratch.
pub fn context_clips(a: &GenerateArgs, window: usize) -> anyhow::Result<(Vec<ContextClip>, f64)> {
    let mut out = Vec::new();
    for spec in &a.context {
        out.push(one_context(spec, window)?);
    }
    if let Some(spec) = &a.contexts {
        out.extend(split_contexts(spec, window)?);
    }
    let Some(first) = out.first() else {
        anyhow::ensure!(
            a.from_scratch,
            "give --context DATA:CLIP[:FRAMES], --contexts DATA:SPLIT:COUNT[:FRAMES] or --from-scratch"
        );
        return Ok((out, 0.5));
    };
    let (frames, interval, id) = (first.clip.len(), first.clip.interval, first.id.clone());
    for c in &out {
        anyhow::ensure!(
            c.clip.len() == frames && (c.clip.interval - interval).abs() < 1e-9,
            "context `{}` has {} frames at {} s, `{id}` {frames} at {interval} s: the contexts of one batch need the same length and interval",
            c.id,
            c.clip.len(),
            c.clip.interval
        );
    }
    Ok((out, interval))
}

/// `--context DATA:CLIP[:FRAMES]`.
fn one_context(spec: &str, window: usize) -> anyhow::Result<ContextClip> {
    // Clip ids may hold ':' themselves (`rand-s3/v0:2`): a numeric suffix is a frame count only when
    // the whole rest is not a clip id.
    let (data, rest) = spec
        .split_once(':')
        .with_context(|| format!("--context {spec}: expected DATA:CLIP or DATA:CLIP:FRAMES"))?;
    let ds = Dataset::open(Path::new(data))?;
    let (index, frames) = match ds.find_clip(rest) {
        Ok(i) => (i, None),
        Err(e) => match rest.rsplit_once(':') {
            Some((clip, f)) if f.parse::<usize>().is_ok() => (ds.find_clip(clip)?, f.parse::<usize>().ok()),
            _ => return Err(e.into()),
        },
    };
    let n = frames.unwrap_or(window).min(ds.clips()[index].frames);
    anyhow::ensure!(n > 0, "--context {spec}: the clip has no frames");
    read_context(&ds, data, index, n)
}

/// `--contexts DATA:SPLIT:COUNT[:FRAMES]`: COUNT clips of SPLIT with at least FRAMES frames (default: the
/// window), evenly spaced over the split.
fn split_contexts(spec: &str, window: usize) -> anyhow::Result<Vec<ContextClip>> {
    let bad = || format!("--contexts {spec}: expected DATA:SPLIT:COUNT or DATA:SPLIT:COUNT:FRAMES");
    let number = |s: &str| s.parse::<usize>().ok();
    let (head, frames) = match spec.rsplit_once(':') {
        Some((h, f))
            if number(f).is_some() && h.rsplit_once(':').is_some_and(|(_, c)| number(c).is_some()) =>
        {
            (h, number(f))
        }
        _ => (spec, None),
    };
    let (rest, count) = head.rsplit_once(':').with_context(bad)?;
    let count = number(count).filter(|&c| c > 0).with_context(bad)?;
    let (data, split) = rest.rsplit_once(':').with_context(bad)?;
    let n = frames.unwrap_or(window);
    let ds = Dataset::open(Path::new(data))?;
    let eligible: Vec<usize> = (0..ds.clips().len())
        .filter(|&i| ds.clips()[i].split == split && ds.clips()[i].frames >= n)
        .collect();
    anyhow::ensure!(
        eligible.len() >= count && n > 0,
        "--contexts {spec}: split `{split}` of {data} has {} clip(s) of at least {n} frames",
        eligible.len()
    );
    (0..count)
        .map(|k| read_context(&ds, data, eligible[k * eligible.len() / count], n))
        .collect()
}

/// The first `n` frames of clip `index` of `ds` (opened from `data`).
fn read_context(ds: &Dataset, data: &str, index: usize, n: usize) -> anyhow::Result<ContextClip> {
    Ok(ContextClip {
        clip: ds.read_window(index, 0, n, 1)?,
        data: data.to_string(),
        id: ds.clips()[index].id.clone(),
    })
}
