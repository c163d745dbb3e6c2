//! The modality plug-in interface of umgen.
//!
//! A scene frame holds several modalities (ego action, map, agents, image, and any a user adds). Each one
//! implements [`Modality`]: it declares a [`ModalitySpec`] (name, vocabulary, tokens per frame, special
//! ids, optional spatial [`Grid`]), turns frames into ids ([`Modality::tokenize`]) and ids back into frame
//! content ([`Modality::detokenize`]), and may expose a pre-trained [`Codebook`].
//!
//! A [`ModalityRegistry`] holds modalities in frame order, refuses duplicate names and derives the
//! [`FrameLayout`]: offsets, each position's modality and allowed ids, start/end positions, the frame
//! length N and a fingerprint that checkpoints use to refuse tokens they were not trained on.
//! A [`ModalityCatalog`] maps config kinds to factories, so a config file can name modalities.
//!
//! A modality may also draw its content on pictures ([`Modality::marks`], as [`Mark`]s).
//!
//! [`Discretizer`] implements the paper's scalar discretisation with clamp counting, for modalities
//! made of real values.
//!
//! ```
//! use std::sync::Arc;
//! use umgen_modality::{DecodeReport, Modality, ModalityRegistry, ModalitySpec, Result};
//! use umgen_scene::{Frame, SceneClip};
//!
//! /// One token per frame: whether the ego is moving.
//! #[derive(Debug)]
//! struct Moving(ModalitySpec);
//! impl Modality for Moving {
//!     fn spec(&self) -> &ModalitySpec { &self.0 }
//!     fn tokenize(&self, clip: &SceneClip, t: usize) -> Result<Vec<u32>> {
//!         Ok(vec![u32::from(clip.frame(t)?.ego.speed > 0.1)])
//!     }
//!     fn detokenize(&self, ids: &[u32], frame: &mut Frame) -> Result<DecodeReport> {
//!         frame.ego.speed = if ids[0] == 1 { 1.0 } else { 0.0 };
//!         Ok(DecodeReport::default())
//!     }
//! }
//!
//! let mut registry = ModalityRegistry::new(true);
//! registry.register(Arc::new(Moving(ModalitySpec::new("moving", "moving", 2, 1))))?;
//! assert_eq!(registry.layout()?.len(), 3); // start, the token, end
//! # Ok::<(), umgen_modality::ModalityError>(())
//! ```

mod base;
mod error;
mod layout;
mod mark;
mod registry;
mod scalar;
mod spec;
mod stops;

pub use base::{DecodeReport, Modality};
pub use error::{ModalityError, Result};
pub use layout::{FrameLayout, Position, Segment, Slot};
pub use mark::Mark;
pub use registry::{Factory, LayoutConfig, ModalityCatalog, ModalityRegistry, parse_settings};
pub use scalar::{Clamp, ClampCount, Discretizer, ScalarBins};
pub use spec::{Codebook, Grid, ModalitySpec, Tracks, downsampling};
pub use stops::Stops;
