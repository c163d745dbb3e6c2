//! Support for umgen's workspace-level integration tests (in `tests/tests/`).
//!
//! [`fixtures`] makes small datasets through the real importer; [`run_fixture`] adds tokenizers and
//! configs for end-to-end CLI runs.

pub mod fixtures;
pub mod run_fixture;
