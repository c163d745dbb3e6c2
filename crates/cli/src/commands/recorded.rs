//! `umgen generate --recorded-ego`: the ego actions each context clip recorded after its context, to force
//! in place of the ego module's, so that `umgen eval` measures the agents (and the rest of the scene)
//! given the real ego motion rather than a mix of the agents' and the ego's errors.

use anyhow::Context;
use std::path::Path;
use umgen::backbone::BackboneSpec;
use umgen::data::Dataset;
use umgen::modality::ModalityRegistry;

/// For each context `(data, clip id)` whose first `context_frames` frames were read, the action tokens
/// (the ego segment's content ids) of its next `frames` frames: `[context][frame][token]`. Errors name
/// the clip that ends too soon, and a model without an action segment.
pub(super) fn recorded_actions(
    contexts: &[(&str, &str)],
    context_frames: usize,
    frames: usize,
    registry: &ModalityRegistry,
    spec: &BackboneSpec,
) -> anyhow::Result<Vec<Vec<Vec<u32>>>> {
    let action = spec
        .action
        .as_ref()
        .context("--recorded-ego: this model has no ego action segment (backbone.action)")?;
    let ego = registry.get(&spec.segments[action.segment].label)?;
    anyhow::ensure!(
        !contexts.is_empty(),
        "--recorded-ego needs context clips (--context or --contexts), not --from-scratch"
    );
    // Contexts usually come from one dataset: open each once, not once per clip.
    let mut opened: Vec<(&str, Dataset)> = Vec::new();
    contexts
        .iter()
        .map(|&(data, id)| {
            let at = match opened.iter().position(|(d, _)| *d == data) {
                Some(i) => i,
                None => {
                    opened.push((data, Dataset::open(Path::new(data))?));
                    opened.len() - 1
                }
            };
            let ds = &opened[at].1;
            let index = ds.find_clip(id)?;
            let have = ds.clips()[index].frames;
            let need = context_frames + frames;
            anyhow::ensure!(
                have >= need,
                "--recorded-ego: clip `{id}` of {data} has {have} frames, {context_frames} of context and \
                 {frames} to generate need {need}"
            );
            let clip = ds.read_window(index, 0, need, 1)?;
            let blocks = ego
                .tokenize_clip(&clip)
                .with_context(|| format!("--recorded-ego: the ego actions of clip `{id}`"))?;
            Ok(blocks[context_frames..].to_vec())
        })
        .collect()
}
