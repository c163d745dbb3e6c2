//! The run configuration: one typed struct over the sections that components own.

use crate::error::{Result, UmgenError};
use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;
use std::path::Path;
use umgen_backbone::BackboneConfig;
use umgen_config::{ConfigError, RawConfig};
use umgen_modality::{LayoutConfig, ModalityCatalog, ModalityError, ModalityRegistry};
use umgen_train::TrainConfig;

/// A complete umgen configuration (`configs/*.toml`).
///
/// Modality tables stay untyped here because modalities are plug-ins: each factory types its own table
/// and reports unknown keys as `modality.<name>.<key>`.
#[derive(Debug, Clone, Deserialize, Serialize)]
#[serde(deny_unknown_fields)]
pub struct UmgenConfig {
    /// Which modalities make a frame, in order.
    pub layout: LayoutConfig,
    /// Settings per modality name.
    #[serde(default)]
    pub modality: BTreeMap<String, toml::Table>,
    /// Model sizes.
    #[serde(default)]
    pub backbone: BackboneConfig,
    /// Training settings.
    #[serde(default)]
    pub train: TrainConfig,
    /// The layers this config came from, to say where a bad key was set.
    #[serde(skip)]
    layers: Option<RawConfig>,
}

impl UmgenConfig {
    /// Loads `path` with `UMGEN__…` environment variables and `--set key=value` overrides on top.
    pub fn load(path: &Path, overrides: &[String]) -> Result<Self> {
        let layers = RawConfig::load(path, overrides)?;
        let mut config: Self = layers.parse()?;
        let problem = config
            .train
            .problem()
            .map(|(key, message)| (format!("train.{key}"), message))
            .or_else(|| {
                config
                    .backbone
                    .problem()
                    .map(|(key, message)| (format!("backbone.{key}"), message))
            });
        if let Some((key, message)) = problem {
            return Err(ConfigError::Key {
                origin: layers.origin(&key),
                key,
                message,
            }
            .into());
        }
        config.layers = Some(layers);
        Ok(config)
    }

    /// Parses a config from TOML text alone (no layering), for tests and examples.
    pub fn from_toml_str(text: &str) -> Result<Self> {
        toml::from_str(text).map_err(|e| UmgenError::Text(e.to_string()))
    }

    /// Builds the modalities in `layout.order` from their tables with `catalog`.
    pub fn registry(&self, catalog: &ModalityCatalog) -> Result<ModalityRegistry> {
        catalog
            .build_registry(&self.layout.order, &self.modality, self.layout.boundary_tokens)
            .map_err(|e| self.locate(e))
    }

    /// The config with every `modality.<name>.tokenizer` that does not exist yet removed, with their
    /// names: for commands that need the layout but not trained tokenizers. The layout fingerprint then
    /// lacks those tokenizers' identity.
    pub fn without_missing_tokenizers(&self) -> (Self, Vec<String>) {
        let mut c = self.clone();
        let mut removed = Vec::new();
        for (name, t) in &mut c.modality {
            let missing = t
                .get("tokenizer")
                .and_then(|v| v.as_str())
                .is_some_and(|p| !Path::new(p).join("vq.json").exists());
            if missing {
                t.remove("tokenizer");
                removed.push(name.clone());
            }
        }
        (c, removed)
    }

    /// The configuration as JSON, for checkpoints and reports.
    pub fn to_json(&self) -> serde_json::Value {
        serde_json::to_value(self).unwrap_or(serde_json::Value::Null)
    }

    /// Adds the layer (file, environment variable, `--set`) to errors about a config key.
    fn locate(&self, e: ModalityError) -> UmgenError {
        match (e, &self.layers) {
            (ModalityError::Config { key, message }, Some(layers)) => UmgenError::Config(ConfigError::Key {
                origin: layers.origin(&key),
                key,
                message,
            }),
            (e, _) => e.into(),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn duplicate_modalities_and_stray_tables_are_refused() {
        let catalog = crate::builtin_catalog().unwrap();
        let dup = UmgenConfig::from_toml_str("[layout]\norder = [\"ego\", \"agent\", \"ego\"]").unwrap();
        let err = dup.registry(&catalog).unwrap_err().to_string();
        assert!(err.contains("duplicate modality name `ego`"), "{err}");
        let stray = UmgenConfig::from_toml_str("[layout]\norder = [\"ego\"]\n[modality.agent]\n").unwrap();
        let err = stray.registry(&catalog).unwrap_err().to_string();
        assert!(
            err.contains("modality.agent") && err.contains("layout.order"),
            "{err}"
        );
        let unknown = UmgenConfig::from_toml_str("[layout]\norder = [\"lidar\"]").unwrap();
        let err = unknown.registry(&catalog).unwrap_err().to_string();
        assert!(
            err.contains("unknown kind `lidar`") && err.contains("agent, ego, image, map"),
            "{err}"
        );
    }

    #[test]
    fn two_modalities_of_one_kind_under_different_names() {
        let catalog = crate::builtin_catalog().unwrap();
        let c = UmgenConfig::from_toml_str(
            "[layout]\norder = [\"ego\", \"near\", \"far\"]\n[modality.near]\nkind = \"agent\"\nmax_agents = 2\n\
             [modality.far]\nkind = \"agent\"\nmax_agents = 3\nx = [-200.0, 200.0]\n",
        )
        .unwrap();
        let r = c.registry(&catalog).unwrap();
        let l = r.layout().unwrap();
        assert_eq!(l.segment("near").unwrap().tokens, 22);
        assert_eq!(l.segment("far").unwrap().tokens, 33);
        assert_eq!(l.segment("far").unwrap().kind, "agent");
    }
}
