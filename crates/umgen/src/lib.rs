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

mod config;
mod error;

pub use config::UmgenConfig;
pub use error::{Result, UmgenError};
pub use umgen_config as config_layers;
pub use umgen_modality as modality;
pub use umgen_scene as scene;

use umgen_modality::{ModalityCatalog, Result as ModalityResult};

/// The catalog of built-in modality kinds: `ego`, `map`, `agent` and `image`. Add your own kinds to it
/// with [`ModalityCatalog::add`] before building a registry.
pub fn builtin_catalog() -> ModalityResult<ModalityCatalog> {
    let mut catalog = ModalityCatalog::new();
    catalog.add(umgen_modality_ego::KIND, umgen_modality_ego::EgoModality::factory)?;
    catalog.add(umgen_modality_map::KIND, umgen_modality_map::MapModality::factory)?;
    catalog.add(
        umgen_modality_agent::KIND,
        umgen_modality_agent::AgentModality::factory,
    )?;
    catalog.add(
        umgen_modality_image::KIND,
        umgen_modality_image::ImageModality::factory,
    )?;
    Ok(catalog)
}
