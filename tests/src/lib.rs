//! Support for umgen's workspace-level integration tests (in `tests/tests/`).
//!
//! [`traffic_lights`] is a complete fifth modality written only against the public trait, the way a
//! user adds one; the tests register it next to the built-ins without touching any built-in crate.
//! [`fixtures`] makes small datasets through the real importer; [`run_fixture`] adds tokenizers and
//! configs for end-to-end CLI runs.

pub mod fixtures;
pub mod run_fixture;
pub mod traffic_lights;
