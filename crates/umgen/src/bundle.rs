//! Export bundles: what `umgen generate` and outside runners load — the backbone weights, the VQ
//! tokenizers, and a manifest with the resolved config, the frame layout and checksums
//! (`docs/export-format.md`).

use crate::config::UmgenConfig;
use crate::error::{Result, UmgenError};
use crate::{backbone_spec, builtin_catalog};
use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use umgen_checkpoint::burn_io::first_non_finite;
use umgen_checkpoint::{CheckpointDir, Loaded, sha256};
use umgen_modality::{ModalityCatalog, ModalityRegistry};

/// The manifest's file name.
pub const BUNDLE_MANIFEST: &str = "manifest.json";
/// The weights' file name.
pub const BUNDLE_WEIGHTS: &str = "model.safetensors";
const FORMAT: &str = "umgen-bundle";
const VERSION: u32 = 1;

/// Element type of the exported weights.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum WeightDtype {
    /// As trained.
    F32,
    /// Rounded to bfloat16 (nearest even): half the size.
    Bf16,
}

/// A file of the bundle.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct BundleFile {
    /// Size in bytes.
    pub bytes: u64,
    /// Lower-case hex SHA-256.
    pub sha256: String,
}

/// `manifest.json`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct BundleManifest {
    /// Always `umgen-bundle`.
    pub format: String,
    /// Format version.
    pub version: u32,
    /// The umgen that wrote it.
    pub umgen_version: String,
    /// Element type of `model.safetensors`.
    pub dtype: WeightDtype,
    /// Training step of the exported checkpoint.
    pub step: u64,
    /// Layout fingerprint (checkpoints and token caches carry the same).
    pub fingerprint: String,
    /// The resolved config; tokenizer paths are relative to the bundle.
    pub config: serde_json::Value,
    /// The frame layout: per-modality offsets, vocabularies, special ids, grids.
    pub layout: serde_json::Value,
    /// The backbone's frame spec: segments, action bins, AMA grid.
    pub backbone: serde_json::Value,
    /// How generation decodes beyond the logits: default history `window`, default `sampling` per
    /// modality, token `groups` (agent slots). Absent in bundles of umgen before 0.1.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub generation: Option<serde_json::Value>,
    /// Every other file of the bundle, by relative path.
    pub files: BTreeMap<String, BundleFile>,
}

fn bundle_err(path: &Path, message: impl Into<String>) -> UmgenError {
    UmgenError::Bundle {
        path: path.to_path_buf(),
        message: message.into(),
    }
}

/// The newest good checkpoint of a run directory, or the checkpoint directory itself.
fn load_checkpoint(dir: &Path) -> Result<Loaded> {
    if dir.join(umgen_checkpoint::MANIFEST).exists() {
        return Ok(umgen_checkpoint::load(dir)?);
    }
    CheckpointDir::new(dir.join("checkpoints"), usize::MAX)
        .load_latest()?
        .ok_or_else(|| bundle_err(dir, "no checkpoint here or in its `checkpoints/`"))
}

/// Safetensors bytes with every tensor converted to `to` (F32 ↔ BF16; bf16 rounds to nearest even, NaN
/// stays NaN), names sorted.
fn convert(bytes: &[u8], to: safetensors::Dtype, path: &Path) -> Result<Vec<u8>> {
    use safetensors::Dtype;
    let st = safetensors::SafeTensors::deserialize(bytes).map_err(|e| bundle_err(path, e.to_string()))?;
    let mut out: Vec<(String, Vec<usize>, Vec<u8>)> = Vec::new();
    for (name, view) in st.tensors() {
        let data: Vec<u8> = match (view.dtype(), to) {
            (a, b) if a == b => view.data().to_vec(),
            (Dtype::F32, Dtype::BF16) => view
                .data()
                .chunks_exact(4)
                .flat_map(|b| {
                    let x = u32::from_le_bytes([b[0], b[1], b[2], b[3]]);
                    let h = if f32::from_bits(x).is_nan() {
                        (x >> 16) as u16 | 0x40
                    } else {
                        ((x + 0x7fff + ((x >> 16) & 1)) >> 16) as u16
                    };
                    h.to_le_bytes()
                })
                .collect(),
            (Dtype::BF16, Dtype::F32) => view
                .data()
                .chunks_exact(2)
                .flat_map(|b| (u32::from(u16::from_le_bytes([b[0], b[1]])) << 16).to_le_bytes())
                .collect(),
            (from, _) => {
                return Err(bundle_err(
                    path,
                    format!("{name}: {from:?} cannot be converted to {to:?}"),
                ));
            }
        };
        out.push((name, view.shape().to_vec(), data));
    }
    out.sort_by(|a, b| a.0.cmp(&b.0));
    let views = out
        .iter()
        .map(|(n, s, d)| {
            safetensors::tensor::TensorView::new(to, s.clone(), d)
                .map(|v| (n.clone(), v))
                .map_err(|e| bundle_err(path, e.to_string()))
        })
        .collect::<Result<Vec<_>>>()?;
    safetensors::tensor::serialize(views, None).map_err(|e| bundle_err(path, e.to_string()))
}

fn write(path: &Path, data: &[u8], files: &mut BTreeMap<String, BundleFile>, rel: &str) -> Result<()> {
    std::fs::write(path, data).map_err(|e| bundle_err(path, e.to_string()))?;
    files.insert(
        rel.to_string(),
        BundleFile {
            bytes: data.len() as u64,
            sha256: sha256(data),
        },
    );
    Ok(())
}

/// Writes the bundle of the checkpoint `checkpoint` (a run directory: its newest good checkpoint) into
/// `out`, which must not exist. Refuses a checkpoint whose tokenizers changed since training (the layout
/// fingerprint would differ). `catalog` builds the config's modalities (`builtin_catalog()` and the
/// user's kinds).
pub fn export_bundle(
    checkpoint: &Path,
    out: &Path,
    dtype: WeightDtype,
    catalog: &ModalityCatalog,
) -> Result<BundleManifest> {
    let loaded = load_checkpoint(checkpoint)?;
    if loaded.manifest.kind != umgen_train::KIND {
        return Err(bundle_err(
            &loaded.dir,
            format!("a `{}` checkpoint, not a backbone", loaded.manifest.kind),
        ));
    }
    let meta = &loaded.manifest.meta;
    let mut config: UmgenConfig = serde_json::from_value(meta["config"].clone())
        .map_err(|e| bundle_err(&loaded.dir, format!("its config: {e}")))?;
    let trained = meta["identity"]["fingerprint"]
        .as_str()
        .unwrap_or_default()
        .to_string();
    let registry = config.registry(catalog)?;
    let layout = registry.layout()?;
    if layout.fingerprint() != trained {
        return Err(bundle_err(
            &loaded.dir,
            "its config's tokenizers no longer match the ones it was trained with (layout fingerprint differs)",
        ));
    }
    let spec = backbone_spec(&registry, &config.backbone)?;
    if let Some(name) = first_non_finite(loaded.file(BUNDLE_WEIGHTS)?)? {
        return Err(bundle_err(
            &loaded.dir,
            format!(
                "its weights of `{name}` hold values that are not finite (a diverged run): export an earlier checkpoint"
            ),
        ));
    }
    if out.exists() {
        return Err(bundle_err(out, "already exists; choose a new directory"));
    }
    std::fs::create_dir_all(out).map_err(|e| bundle_err(out, e.to_string()))?;
    let mut files = BTreeMap::new();
    let weights = loaded.file(BUNDLE_WEIGHTS)?;
    let weights = match dtype {
        WeightDtype::F32 => weights.to_vec(),
        WeightDtype::Bf16 => convert(weights, safetensors::Dtype::BF16, &loaded.dir)?,
    };
    write(&out.join(BUNDLE_WEIGHTS), &weights, &mut files, BUNDLE_WEIGHTS)?;
    for (name, table) in &mut config.modality {
        let Some(dir) = table.get("tokenizer").and_then(|v| v.as_str()).map(PathBuf::from) else {
            continue;
        };
        let rel = format!("tokenizers/{name}");
        std::fs::create_dir_all(out.join(&rel)).map_err(|e| bundle_err(out, e.to_string()))?;
        for f in ["vq.json", "vq.safetensors"] {
            let src = dir.join(f);
            let data = std::fs::read(&src).map_err(|e| bundle_err(&src, e.to_string()))?;
            write(&out.join(&rel).join(f), &data, &mut files, &format!("{rel}/{f}"))?;
        }
        table.insert("tokenizer".into(), toml::Value::String(rel));
    }
    let manifest = BundleManifest {
        format: FORMAT.into(),
        version: VERSION,
        umgen_version: env!("CARGO_PKG_VERSION").into(),
        dtype,
        step: loaded.manifest.step,
        fingerprint: trained,
        config: config.to_json(),
        layout: serde_json::json!({"n": layout.len(), "segments": layout.segments()}),
        backbone: serde_json::to_value(&spec).unwrap_or_default(),
        generation: Some(crate::generation_manifest(&registry, &config)?),
        files,
    };
    let text = serde_json::to_vec_pretty(&manifest).map_err(|e| bundle_err(out, e.to_string()))?;
    let path = out.join(BUNDLE_MANIFEST);
    std::fs::write(&path, text).map_err(|e| bundle_err(&path, e.to_string()))?;
    Ok(manifest)
}

/// Writes `data` as `rel` into the bundle `dir` and lists it in the manifest with its size and checksum.
pub(crate) fn add_file(dir: &Path, rel: &str, data: &[u8]) -> Result<()> {
    let path = dir.join(BUNDLE_MANIFEST);
    let text = std::fs::read(&path).map_err(|e| bundle_err(&path, e.to_string()))?;
    let mut manifest: BundleManifest =
        serde_json::from_slice(&text).map_err(|e| bundle_err(&path, e.to_string()))?;
    write(&dir.join(rel), data, &mut manifest.files, rel)?;
    let text = serde_json::to_vec_pretty(&manifest).map_err(|e| bundle_err(&path, e.to_string()))?;
    std::fs::write(&path, text).map_err(|e| bundle_err(&path, e.to_string()))
}

/// An opened, verified bundle.
#[derive(Debug, Clone)]
pub struct Bundle {
    /// Its directory.
    pub dir: PathBuf,
    /// Its manifest.
    pub manifest: BundleManifest,
    /// Its config, tokenizer paths resolved against `dir`.
    pub config: UmgenConfig,
}

impl Bundle {
    /// Opens `dir`: every file the manifest lists must be there with its checksum, and the config with the
    /// bundled tokenizers must give the manifest's layout fingerprint.
    pub fn open(dir: &Path) -> Result<Self> {
        Ok(Self::open_with(dir, &builtin_catalog()?)?.0)
    }

    /// [`open`](Self::open), building the modalities with `catalog` (e.g. tokenizers on a GPU); returns
    /// them too, so that callers need not build them again.
    pub fn open_with(dir: &Path, catalog: &ModalityCatalog) -> Result<(Self, ModalityRegistry)> {
        let path = dir.join(BUNDLE_MANIFEST);
        let text = std::fs::read(&path).map_err(|e| bundle_err(&path, e.to_string()))?;
        let manifest: BundleManifest =
            serde_json::from_slice(&text).map_err(|e| bundle_err(&path, e.to_string()))?;
        if manifest.format != FORMAT || manifest.version != VERSION {
            return Err(bundle_err(
                &path,
                format!(
                    "format {} v{}, expected {FORMAT} v{VERSION}",
                    manifest.format, manifest.version
                ),
            ));
        }
        if !manifest.files.contains_key(BUNDLE_WEIGHTS) {
            return Err(bundle_err(&path, format!("lists no {BUNDLE_WEIGHTS}")));
        }
        for (rel, f) in &manifest.files {
            let p = dir.join(rel);
            let data = std::fs::read(&p)
                .map_err(|e| bundle_err(&p, format!("listed in the manifest but unreadable: {e}")))?;
            if data.len() as u64 != f.bytes || sha256(&data) != f.sha256 {
                return Err(bundle_err(
                    &p,
                    "does not match the manifest's size and checksum (damaged or replaced)",
                ));
            }
            if rel == BUNDLE_WEIGHTS
                && let Some(name) = first_non_finite(&data)?
            {
                return Err(bundle_err(
                    &p,
                    format!(
                        "the weights of `{name}` hold values that are not finite (exported from a diverged run)"
                    ),
                ));
            }
        }
        let mut config: UmgenConfig = serde_json::from_value(manifest.config.clone())
            .map_err(|e| bundle_err(&path, format!("config: {e}")))?;
        for table in config.modality.values_mut() {
            if let Some(rel) = table
                .get("tokenizer")
                .and_then(|v| v.as_str())
                .map(str::to_string)
            {
                table.insert(
                    "tokenizer".into(),
                    toml::Value::String(dir.join(rel).display().to_string()),
                );
            }
        }
        let registry = config.registry(catalog)?;
        if registry.layout()?.fingerprint() != manifest.fingerprint {
            return Err(bundle_err(
                &path,
                "its tokenizers and config do not give the layout it was exported with",
            ));
        }
        Ok((
            Self {
                dir: dir.to_path_buf(),
                manifest,
                config,
            },
            registry,
        ))
    }

    /// The weights' bytes (safetensors), as exported.
    pub fn weights(&self) -> Result<Vec<u8>> {
        let p = self.dir.join(BUNDLE_WEIGHTS);
        std::fs::read(&p).map_err(|e| bundle_err(&p, e.to_string()))
    }

    /// The weights as f32 safetensors (bf16 bundles widened), for loading into an f32 model.
    pub fn weights_f32(&self) -> Result<Vec<u8>> {
        let w = self.weights()?;
        match self.manifest.dtype {
            WeightDtype::F32 => Ok(w),
            WeightDtype::Bf16 => convert(&w, safetensors::Dtype::F32, &self.dir.join(BUNDLE_WEIGHTS)),
        }
    }
}
