//! The modality registry (modalities in frame order) and the catalog of modality factories.

use crate::base::{DecodeReport, Modality};
use crate::error::{ModalityError, Result};
use crate::layout::{FrameLayout, check_block};
use serde::de::DeserializeOwned;
use std::collections::BTreeMap;
use std::sync::Arc;
use umgen_scene::{Frame, SceneClip};

/// The modalities of a frame, in frame order, and the layout derived from them.
#[derive(Debug, Clone)]
pub struct ModalityRegistry {
    modalities: Vec<Arc<dyn Modality>>,
    boundary_tokens: bool,
    layout: Option<FrameLayout>,
}

impl ModalityRegistry {
    /// An empty registry; `boundary_tokens` wraps every block in its own start and end tokens.
    pub fn new(boundary_tokens: bool) -> Self {
        Self {
            modalities: Vec::new(),
            boundary_tokens,
            layout: None,
        }
    }

    /// Appends a modality to the frame. A second modality with the same name is refused.
    pub fn register(&mut self, modality: Arc<dyn Modality>) -> Result<()> {
        let name = &modality.spec().name;
        if self.modalities.iter().any(|m| &m.spec().name == name) {
            return Err(ModalityError::DuplicateName { name: name.clone() });
        }
        let mut all = self.modalities.clone();
        all.push(modality);
        let layout = layout_of(&all, self.boundary_tokens)?;
        self.modalities = all;
        self.layout = Some(layout);
        Ok(())
    }

    /// Modalities in frame order.
    pub fn modalities(&self) -> &[Arc<dyn Modality>] {
        &self.modalities
    }

    /// The modality called `name`.
    pub fn get(&self, name: &str) -> Result<&Arc<dyn Modality>> {
        self.modalities
            .iter()
            .find(|m| m.spec().name == name)
            .ok_or_else(|| ModalityError::UnknownModality { name: name.into() })
    }

    /// The frame layout.
    pub fn layout(&self) -> Result<&FrameLayout> {
        self.layout.as_ref().ok_or(ModalityError::Empty)
    }

    /// One row of N ids per frame of `clip`, start and end tokens included.
    pub fn tokenize_clip(&self, clip: &SceneClip) -> Result<Vec<Vec<u32>>> {
        let layout = self.layout()?;
        let mut per_modality = Vec::with_capacity(self.modalities.len());
        for (m, seg) in self.modalities.iter().zip(layout.segments()) {
            let blocks = m.tokenize_clip(clip)?;
            if blocks.len() != clip.len() {
                return Err(ModalityError::Tokenizer {
                    modality: seg.modality.clone(),
                    message: format!("returned {} frames for a clip of {}", blocks.len(), clip.len()),
                });
            }
            for b in &blocks {
                check_block(seg, b)?;
            }
            per_modality.push(blocks);
        }
        (0..clip.len())
            .map(|t| {
                let blocks: Vec<Vec<u32>> = per_modality
                    .iter_mut()
                    .map(|b| std::mem::take(&mut b[t]))
                    .collect();
                layout.assemble(&blocks)
            })
            .collect()
    }

    /// Decodes one frame row into `frame`, each modality writing its own part.
    pub fn detokenize(&self, row: &[u32], frame: &mut Frame) -> Result<DecodeReport> {
        self.detokenize_except(row, frame, &[])
    }

    /// [`detokenize`](Self::detokenize) without the modalities of the kinds `skip`, whose parts of
    /// `frame` stay as they were: for callers that drop those parts anyway (a VQ decoder is most of a
    /// frame's decoding time).
    pub fn detokenize_except(&self, row: &[u32], frame: &mut Frame, skip: &[&str]) -> Result<DecodeReport> {
        let blocks = self.layout()?.split(row)?;
        let mut report = DecodeReport::default();
        for (m, block) in self.modalities.iter().zip(blocks) {
            if !skip.contains(&m.spec().kind.as_str()) {
                report.malformed += m.detokenize(block, frame)?.malformed;
            }
        }
        Ok(report)
    }
}

fn layout_of(modalities: &[Arc<dyn Modality>], boundary: bool) -> Result<FrameLayout> {
    let specs: Vec<_> = modalities.iter().map(|m| (m.spec(), m.settings())).collect();
    FrameLayout::new(&specs, boundary)
}

/// The `[layout]` section of a config: which modalities make a frame, in which order.
#[derive(Debug, Clone, PartialEq, Eq, serde::Deserialize, serde::Serialize)]
#[serde(deny_unknown_fields)]
pub struct LayoutConfig {
    /// Modality names in frame order; each is built from `[modality.<name>]`.
    pub order: Vec<String>,
    /// Whether each modality's block is wrapped by its own start and end tokens.
    #[serde(default = "default_true")]
    pub boundary_tokens: bool,
}

fn default_true() -> bool {
    true
}

/// Builds a modality from its name and its config table (the `modality.<name>` table, `kind` removed).
pub type Factory = Box<dyn Fn(&str, &toml::Table) -> Result<Arc<dyn Modality>> + Send + Sync>;

/// Factories by kind: how config names turn into modalities. Register new kinds with
/// [`ModalityCatalog::add`]; no built-in crate needs to change.
#[derive(Default)]
pub struct ModalityCatalog {
    factories: BTreeMap<String, Factory>,
}

impl std::fmt::Debug for ModalityCatalog {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("ModalityCatalog")
            .field("kinds", &self.factories.keys().collect::<Vec<_>>())
            .finish()
    }
}

impl ModalityCatalog {
    /// An empty catalog.
    pub fn new() -> Self {
        Self::default()
    }

    /// Adds a factory for `kind`; a kind can be added once.
    pub fn add<F>(&mut self, kind: &str, factory: F) -> Result<()>
    where
        F: Fn(&str, &toml::Table) -> Result<Arc<dyn Modality>> + Send + Sync + 'static,
    {
        if self.factories.contains_key(kind) {
            return Err(ModalityError::DuplicateKind { kind: kind.into() });
        }
        self.factories.insert(kind.into(), Box::new(factory));
        Ok(())
    }

    /// Known kinds, sorted.
    pub fn kinds(&self) -> impl Iterator<Item = &str> {
        self.factories.keys().map(String::as_str)
    }

    /// Builds modality `name` from its table. The table's `kind` key picks the factory; without it the
    /// kind is the name.
    pub fn build(&self, name: &str, table: &toml::Table) -> Result<Arc<dyn Modality>> {
        let mut table = table.clone();
        let kind = match table.remove("kind") {
            None => name.to_string(),
            Some(toml::Value::String(k)) => k,
            Some(other) => {
                return Err(ModalityError::Config {
                    key: format!("modality.{name}.kind"),
                    message: format!("expected a string, found {}", other.type_str()),
                });
            }
        };
        let factory = self
            .factories
            .get(&kind)
            .ok_or_else(|| ModalityError::UnknownKind {
                name: name.into(),
                kind: kind.clone(),
                known: self.kinds().collect::<Vec<_>>().join(", "),
            })?;
        let modality = factory(name, &table)?;
        if modality.spec().name != name {
            return Err(ModalityError::InvalidSpec {
                modality: name.into(),
                reason: format!("factory `{kind}` named it `{}`", modality.spec().name),
            });
        }
        Ok(modality)
    }

    /// A registry from a frame order and per-modality tables. Every name in `order` is built (a missing
    /// table means all defaults); a table for a name not in `order` is an error, as is a repeated name.
    pub fn build_registry(
        &self,
        order: &[String],
        tables: &BTreeMap<String, toml::Table>,
        boundary_tokens: bool,
    ) -> Result<ModalityRegistry> {
        if order.is_empty() {
            return Err(ModalityError::Empty);
        }
        if let Some((_, name)) = order.iter().enumerate().find(|(i, n)| order[..*i].contains(n)) {
            return Err(ModalityError::DuplicateName { name: name.clone() });
        }
        if let Some(extra) = tables.keys().find(|k| !order.contains(k)) {
            return Err(ModalityError::Config {
                key: format!("modality.{extra}"),
                message: format!(
                    "configured but not listed in `layout.order` ({})",
                    order.join(", ")
                ),
            });
        }
        let mut registry = ModalityRegistry::new(boundary_tokens);
        let empty = toml::Table::new();
        for name in order {
            registry.register(self.build(name, tables.get(name).unwrap_or(&empty))?)?;
        }
        Ok(registry)
    }
}

/// Deserialises a modality's settings from its table; errors carry the full key path
/// (`modality.<name>.<key>`). Use `#[serde(deny_unknown_fields)]` on `T` so that typos are caught.
pub fn parse_settings<T: DeserializeOwned>(name: &str, table: &toml::Table) -> Result<T> {
    let de = toml::Value::Table(table.clone());
    serde_path_to_error::deserialize(de).map_err(|e| {
        let path = e.path().to_string();
        let key = if path == "." {
            format!("modality.{name}")
        } else {
            format!("modality.{name}.{path}")
        };
        ModalityError::Config {
            key,
            message: first_line(&e.into_inner().to_string()),
        }
    })
}

/// The first line of a deserialiser message: toml appends "in `key`" lines that repeat the key path.
pub(crate) fn first_line(message: &str) -> String {
    message.lines().next().unwrap_or_default().trim_end().to_string()
}
