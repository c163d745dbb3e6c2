//! The golden file of an export bundle (`umgen export --golden N`): windows of tokens and the logits
//! umgen's model computes for them, so that a runner outside umgen can check that it computes the same
//! function (docs/export-format.md, `runners/python`).

use crate::bundle::{Bundle, add_file};
use crate::error::{Result, UmgenError};
use crate::{agent_slot_groups, backbone_spec, history_window};
use burn::backend::Flex;
use burn::tensor::{Int, Tensor, TensorData};
use rand::{Rng, SeedableRng, rngs::StdRng};
use safetensors::Dtype;
use std::path::Path;
use umgen_backbone::{Backbone, BackboneSpec};
use umgen_modality::ModalityCatalog;

/// The golden file's name in the bundle.
pub const GOLDEN_FILE: &str = "golden.safetensors";

/// Writes [`GOLDEN_FILE`] into the bundle `dir` and lists it in the manifest: `windows` windows of
/// `window + 1` frames (the bundle's default history window, [`history_window`]) of well-formed random
/// tokens drawn with `seed` (`tokens`, i64 `[windows, frames, N]`), and the f32 logits umgen's model
/// computes for them on the CPU: every segment's TAR and OAR head on the last predicted frame
/// (`tar.<modality>`, `oar.<modality>`, `[windows, tokens, vocab]`; it attends to every earlier frame)
/// and the ego module's on every frame (`ego`, `[windows, frames − 1, q, vocab]`). Random tokens reach
/// every branch that real ones do (slots moved out of range, empty slots, large turns). Returns the
/// file's size in bytes. `catalog` builds the bundle's modalities.
pub fn write_golden(dir: &Path, windows: usize, seed: u64, catalog: &ModalityCatalog) -> Result<u64> {
    let fail = |message: String| UmgenError::Bundle {
        path: dir.join(GOLDEN_FILE),
        message,
    };
    if windows == 0 {
        return Err(fail("--golden needs at least one window".into()));
    }
    let (bundle, registry) = Bundle::open_with(dir, catalog)?;
    let cfg = bundle.config.backbone.for_inference();
    let spec = backbone_spec(&registry, &cfg)?;
    let dev = Default::default();
    let model = Backbone::<Flex>::new(&cfg, &spec, &dev)?;
    let model =
        umgen_checkpoint::burn_io::weights_from_bytes(model, bundle.weights_f32()?, "bundle weights")?;
    let frames = history_window(&bundle.config) + 1;
    let slots = agent_slot_groups(&registry, &bundle.config)?;
    let mut rng = StdRng::seed_from_u64(seed);
    let ids: Vec<i64> = (0..windows * frames)
        .flat_map(|_| random_frame(&spec, slots.as_ref(), &mut rng))
        .collect();
    let n = spec.n;
    let tokens = Tensor::<Flex, 3, Int>::from_data(TensorData::new(ids.clone(), [windows, frames, n]), &dev);
    let logits = model.forced_logits(tokens)?;
    let last = |x: Tensor<Flex, 4>| {
        let [b, t, l, v] = x.dims();
        x.narrow(1, t - 1, 1).reshape([b, l, v])
    };
    let mut out: Vec<(String, Vec<usize>, Vec<u8>)> = vec![(
        "tokens".into(),
        vec![windows, frames, n],
        ids.iter().flat_map(|x| x.to_le_bytes()).collect(),
    )];
    let layout = registry.layout()?;
    for ((seg, tar), oar) in layout.segments().iter().zip(logits.tar).zip(logits.oar) {
        out.push(f32_entry(format!("tar.{}", seg.modality), last(tar).into_data()));
        out.push(f32_entry(format!("oar.{}", seg.modality), last(oar).into_data()));
    }
    if let Some(ego) = logits.ego {
        out.push(f32_entry("ego".into(), ego.into_data()));
    }
    let views = out
        .iter()
        .map(|(name, shape, bytes)| {
            let dtype = if name == "tokens" { Dtype::I64 } else { Dtype::F32 };
            safetensors::tensor::TensorView::new(dtype, shape.clone(), bytes)
                .map(|v| (name.clone(), v))
                .map_err(|e| fail(e.to_string()))
        })
        .collect::<Result<Vec<_>>>()?;
    let bytes = safetensors::tensor::serialize(views, None).map_err(|e| fail(e.to_string()))?;
    let size = bytes.len() as u64;
    add_file(dir, GOLDEN_FILE, &bytes)?;
    Ok(size)
}

/// A named f32 tensor's shape and little-endian bytes.
fn f32_entry(name: String, data: TensorData) -> (String, Vec<usize>, Vec<u8>) {
    let shape = data.shape.to_vec();
    let bytes = data.iter::<f32>().flat_map(f32::to_le_bytes).collect();
    (name, shape, bytes)
}

/// One frame of random tokens that decodes: boundary tokens in place, content ids in their vocabularies,
/// and each agent slot either empty (all pad) or values and a category.
fn random_frame(
    spec: &BackboneSpec,
    slots: Option<&umgen_generate::TokenGroups>,
    rng: &mut StdRng,
) -> Vec<i64> {
    let mut row = vec![0i64; spec.n];
    for s in &spec.segments {
        let block = &mut row[s.block_start..s.block_start + s.block_len];
        for (p, id) in (s.block_start..).zip(block.iter_mut()) {
            *id = if p < s.offset {
                s.vocab as i64
            } else if p >= s.offset + s.tokens {
                s.vocab as i64 + 1
            } else {
                rng.random_range(0..s.vocab as i64)
            };
        }
    }
    if let Some(g) = slots {
        for k in 0..g.count {
            let first = g.first + k * g.size;
            let empty = rng.random_bool(0.5);
            for j in 0..g.size {
                row[first + j] = i64::from(if empty {
                    g.pad
                } else if j + 1 == g.size {
                    rng.random_range(g.last.clone())
                } else {
                    rng.random_range(0..g.values)
                });
            }
        }
    }
    row
}
