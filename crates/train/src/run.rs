//! What a run trains ([`RunSpec`]), what a resumed run, or another rank, must share with it, and how a
//! run takes its directory.

use crate::config::TrainConfig;
use crate::error::{Result, TrainError};
use umgen_backbone::{BackboneConfig, BackboneSpec};
use umgen_checkpoint::CheckpointDir;

/// What a run trains.
#[derive(Debug, Clone)]
pub struct RunSpec {
    /// Model sizes.
    pub backbone: BackboneConfig,
    /// The frame the model is built for.
    pub spec: BackboneSpec,
    /// Training settings.
    pub train: TrainConfig,
    /// Frame layout fingerprint; checkpoints and token caches must match it.
    pub fingerprint: String,
    /// The resolved configuration, saved with every checkpoint.
    pub config: serde_json::Value,
}

impl RunSpec {
    /// What a resumed run must share with the checkpoint.
    pub(crate) fn identity(&self) -> serde_json::Value {
        let mut backbone = serde_json::to_value(&self.backbone).unwrap_or(serde_json::Value::Null);
        // How fresh weights start does not matter to a resumed run (its weights come from the checkpoint)
        // nor to other ranks (they receive rank 0's weights); runs from before the setting stay resumable.
        if let Some(o) = backbone.as_object_mut() {
            o.remove("ordinal_init");
            // Off, `ego_last`, `track_accel` and `track` leave no trace in the model: runs from before them resume.
            for flag in ["ego_last", "track_accel"] {
                if o.get(flag) == Some(&serde_json::Value::Bool(false)) {
                    o.remove(flag);
                }
            }
            if o.get("track").is_none_or(|t| t.is_null() || t == "") {
                o.remove("track");
                o.remove("step_s");
            }
        }
        serde_json::json!({"fingerprint": self.fingerprint, "backbone": backbone, "train": self.train.identity()})
    }

    /// A digest of everything that must be equal on every rank of a data-parallel run.
    pub fn identity_digest(&self) -> String {
        umgen_checkpoint::sha256(self.identity().to_string().as_bytes())
    }
}

/// Which top-level keys of two identities differ, in words.
pub(crate) fn describe_difference(saved: &serde_json::Value, now: &serde_json::Value) -> String {
    let keys = ["fingerprint", "backbone", "train"];
    let differing: Vec<String> = keys
        .iter()
        .filter(|k| saved.get(*k) != now.get(*k))
        .map(|k| {
            match (
                saved.get(*k).and_then(|v| v.as_object()),
                now.get(*k).and_then(|v| v.as_object()),
            ) {
                (Some(a), Some(b)) => {
                    let inner: std::collections::BTreeSet<&str> = a
                        .keys()
                        .chain(b.keys())
                        .filter(|x| a.get(*x) != b.get(*x))
                        .map(String::as_str)
                        .collect();
                    format!("{k} ({})", inner.into_iter().collect::<Vec<_>>().join(", "))
                }
                _ => (*k).to_string(),
            }
        })
        .collect();
    format!("it was trained with another {}", differing.join(" and "))
}

/// Takes `out_dir` for a run that passed its checks: sets aside checkpoints newer than the one it resumes
/// from (they failed to verify), removes what interrupted saves left, and writes `config.json`. A run
/// refused before this point leaves the directory as it was.
pub(crate) fn claim_run_dir(run: &RunSpec, ckpts: &CheckpointDir, step: u64) -> Result<()> {
    for moved in ckpts.set_aside_newer(step)? {
        tracing::warn!(
            "set aside {} (it did not verify; the run continues from step {step})",
            moved.display()
        );
    }
    for (path, bytes) in ckpts.remove_stale_temporaries()? {
        tracing::info!(
            "removed {} ({bytes} bytes), left by an interrupted checkpoint save",
            path.display()
        );
    }
    let out = &run.train.out_dir;
    let io = |error: std::io::Error| TrainError::RunDir {
        path: out.clone(),
        message: format!("writing config.json: {error}"),
    };
    std::fs::create_dir_all(out).map_err(io)?;
    let text = serde_json::to_vec_pretty(&run.config).map_err(|e| TrainError::Setup(e.to_string()))?;
    std::fs::write(out.join("config.json"), text).map_err(io)
}
