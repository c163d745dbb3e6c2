//! umgen trains and runs UMGen-style multimodal driving-scene generators.
//!
//! This crate is the facade: it re-exports the component crates, wires the built-in modalities
//! ([`builtin_catalog`]) and defines the run configuration ([`UmgenConfig`]) whose sections the
//! components own.
//!
//! ```
//! let catalog = umgen::builtin_catalog()?;
//! let config = umgen::UmgenConfig::from_toml_str(r#"
//!     [layout]
//!     order = ["ego", "agent"]
//!     [modality.agent]
//!     max_agents = 4
//! "#)?;
//! let registry = config.registry(&catalog)?;
//! let layout = registry.layout()?;
//! assert_eq!(layout.len(), (1 + 3 + 1) + (1 + 4 * 11 + 1));
//! # Ok::<(), umgen::UmgenError>(())
//! ```

mod bundle;
mod config;
mod error;
mod golden;
mod model;
mod rules;
mod tokenize;
mod vq;

pub use bundle::{
    BUNDLE_MANIFEST, BUNDLE_WEIGHTS, Bundle, BundleFile, BundleManifest, WeightDtype, export_bundle,
};
pub use config::UmgenConfig;
pub use error::{Result, UmgenError};
pub use golden::{GOLDEN_FILE, write_golden};
pub use model::backbone_spec;
pub use rules::{
    EGO_BOX_M, agent_groups, agent_segment, agent_slot_groups, generation_manifest, history_window,
};
pub use tokenize::{TokenizeReport, tokenize_dataset, tokens_missing};
pub use umgen_backbone as backbone;
pub use umgen_checkpoint as checkpoint;
pub use umgen_config as config_layers;
pub use umgen_data as data;
pub use umgen_dist as dist;
pub use umgen_generate as generate;
pub use umgen_modality as modality;
pub use umgen_modality_agent as modality_agent;
pub use umgen_modality_image as modality_image;
pub use umgen_modality_map as modality_map;
pub use umgen_ops as ops;
pub use umgen_optim as optim;
pub use umgen_scene as scene;
pub use umgen_tokenizer_vq as tokenizer_vq;
pub use umgen_train as train;
pub use vq::{DatasetRasters, VqTarget, vq_target};

use umgen_modality::{ModalityCatalog, Result as ModalityResult};

/// The built-in catalog with VQ tokenizers (map, image) loaded by `loader` (for example onto a GPU).
pub fn builtin_catalog_with(loader: umgen_tokenizer_vq::CodecLoader) -> ModalityResult<ModalityCatalog> {
    let mut catalog = ModalityCatalog::new();
    catalog.add(umgen_modality_ego::KIND, umgen_modality_ego::EgoModality::factory)?;
    catalog.add(
        umgen_modality_map::KIND,
        umgen_modality_map::factory_with(loader.clone()),
    )?;
    catalog.add(
        umgen_modality_agent::KIND,
        umgen_modality_agent::AgentModality::factory,
    )?;
    catalog.add(
        umgen_modality_image::KIND,
        umgen_modality_image::factory_with(loader),
    )?;
    Ok(catalog)
}

/// The catalog of built-in modality kinds: `ego`, `map`, `agent` and `image`, with VQ tokenizers on the
/// CPU. Add your own kinds to it with [`ModalityCatalog::add`] before building a registry.
pub fn builtin_catalog() -> ModalityResult<ModalityCatalog> {
    builtin_catalog_with(umgen_tokenizer_vq::cpu_loader())
}
