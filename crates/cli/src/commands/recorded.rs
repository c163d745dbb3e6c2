//! `umgen generate --recorded MODALITY` (and `--recorded-ego`): modalities as each context clip recorded
//! them after its context, placed in the generated frames instead of drawn. The ego action replaces the
//! ego module's, so that `umgen eval` measures the agents given the real ego motion; any other modality
//! conditions the rest of the frame on what really happened (the agents given the real traffic lights,
//! or the real map).

use crate::cli::GenerateArgs;
use anyhow::Context;
use std::path::Path;
use umgen::backbone::BackboneSpec;
use umgen::data::Dataset;
use umgen::generate::Control;
use umgen::modality::ModalityRegistry;

/// The layout label of the ego action's segment, if the model has one.
fn action_label(spec: &BackboneSpec) -> Option<&str> {
    spec.action
        .as_ref()
        .map(|x| spec.segments[x.segment].label.as_str())
}

/// The modalities `--recorded` (comma-separated or repeated) and `--recorded-ego` name, each once, in the
/// order given (`--recorded-ego` names the ego action's modality).
fn labels(a: &GenerateArgs, spec: &BackboneSpec) -> Vec<String> {
    let ego = a
        .recorded_ego
        .then(|| action_label(spec).unwrap_or("ego").to_string());
    let mut labels: Vec<String> = Vec::new();
    for l in a
        .recorded
        .iter()
        .flat_map(|x| x.split(','))
        .map(str::trim)
        .filter(|l| !l.is_empty())
        .map(str::to_string)
        .chain(ego)
    {
        if !labels.contains(&l) {
            labels.push(l);
        }
    }
    labels
}

/// The recorded modalities of every context clip's generated frames (`--recorded`, `--recorded-ego`);
/// refuses what the control file also sets, and the ego action of a model without one.
pub(super) fn modalities(
    a: &GenerateArgs,
    contexts: &[super::contexts::ContextClip],
    context_rows: &[Vec<Vec<u32>>],
    control: &Control,
    registry: &ModalityRegistry,
    spec: &BackboneSpec,
) -> anyhow::Result<Vec<Recorded>> {
    let labels = labels(a, spec);
    if labels.is_empty() {
        return Ok(Vec::new());
    }
    anyhow::ensure!(
        !a.recorded_ego || spec.action.is_some(),
        "--recorded-ego: this model has no ego action segment (backbone.action)"
    );
    let action = action_label(spec);
    let agents = super::agents::agent_modality(registry)?.map(|(_, seg)| seg.modality.clone());
    for l in &labels {
        anyhow::ensure!(
            Some(l.as_str()) != action || control.ego.is_empty(),
            "--recorded {l} (the ego action) and the control file's [[ego]] entries both set the ego action"
        );
        anyhow::ensure!(
            Some(l) != agents.as_ref() || control.agent.is_empty(),
            "--recorded {l} (the agents) and the control file's [[agent]] entries both set agents"
        );
    }
    let ids: Vec<(&str, &str)> = contexts
        .iter()
        .map(|c| (c.data.as_str(), c.id.as_str()))
        .collect();
    let n = context_rows.first().map_or(0, Vec::len);
    let flag = match a.recorded.is_empty() {
        true => "--recorded-ego".to_string(),
        false => format!("--recorded {}", labels.join(",")),
    };
    recorded(&flag, &ids, n, a.frames, &labels, registry, spec)
}

/// One recorded modality: its segment in the layout and, per context, its content ids in each generated
/// frame, `[context][frame][token]`.
pub(super) struct Recorded {
    /// The segment's index in the layout.
    pub segment: usize,
    /// `[context][frame][token]`.
    pub blocks: Vec<Vec<Vec<u32>>>,
}

/// For each context `(data, clip id)` whose first `context_frames` frames were read, the content tokens
/// of the modalities `labels` (layout labels) in its next `frames` frames. Errors begin with `flag` (the
/// option as given) and name an unknown label, the clip that ends too soon, and the modality that fails
/// to tokenize.
pub(super) fn recorded(
    flag: &str,
    contexts: &[(&str, &str)],
    context_frames: usize,
    frames: usize,
    labels: &[String],
    registry: &ModalityRegistry,
    spec: &BackboneSpec,
) -> anyhow::Result<Vec<Recorded>> {
    anyhow::ensure!(
        !contexts.is_empty(),
        "{flag} needs context clips (--context or --contexts), not --from-scratch"
    );
    let segments = labels
        .iter()
        .map(|l| {
            spec.segments.iter().position(|s| &s.label == l).with_context(|| {
                let have: Vec<&str> = spec.segments.iter().map(|s| s.label.as_str()).collect();
                format!(
                    "{flag}: `{l}` is none of this model's modalities, {}",
                    have.join(", ")
                )
            })
        })
        .collect::<anyhow::Result<Vec<usize>>>()?;
    let mut out: Vec<Recorded> = segments
        .iter()
        .map(|&segment| Recorded {
            segment,
            blocks: Vec::with_capacity(contexts.len()),
        })
        .collect();
    // Contexts usually come from one dataset: open each once, not once per clip.
    let mut opened: Vec<(&str, Dataset)> = Vec::new();
    // Per context: its dataset in `opened`, its clip there and the clip's frames.
    let mut clips = Vec::with_capacity(contexts.len());
    for &(data, id) in contexts {
        let at = match opened.iter().position(|(d, _)| *d == data) {
            Some(i) => i,
            None => {
                opened.push((data, Dataset::open(Path::new(data))?));
                opened.len() - 1
            }
        };
        let ds = &opened[at].1;
        let index = ds.find_clip(id)?;
        clips.push((at, index, ds.clips()[index].frames));
    }
    // Every clip that ends too soon at once, and what would fit them all: the first error is then the
    // last.
    let need = context_frames + frames;
    let short: Vec<usize> = (0..clips.len()).filter(|&i| clips[i].2 < need).collect();
    if let Some(&first) = short.first() {
        let ((data, id), have) = (contexts[first], clips[first].2);
        let fewest = clips.iter().map(|c| c.2).min().unwrap_or(have);
        let fit = match fewest.checked_sub(context_frames).filter(|&n| n > 0) {
            Some(n) => format!("--frames {n} fits every one"),
            None => format!("the shortest holds nothing past the {context_frames} frames of context"),
        };
        anyhow::bail!(
            "{flag}: clip `{id}` of {data} has {have} frames, {context_frames} of context and {frames} \
             to generate need {need} ({} of the {} contexts end too soon; {fit})",
            short.len(),
            contexts.len()
        );
    }
    for (&(_, id), &(at, index, _)) in contexts.iter().zip(&clips) {
        let clip = opened[at].1.read_window(index, 0, need, 1)?;
        for (r, l) in out.iter_mut().zip(labels) {
            let blocks = registry
                .get(l)?
                .tokenize_clip(&clip)
                .with_context(|| format!("{flag}: the `{l}` tokens of clip `{id}`"))?;
            r.blocks.push(blocks[context_frames..].to_vec());
        }
    }
    Ok(out)
}
