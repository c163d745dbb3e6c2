//! Workspace-level integration tests, one module per concern.
#![allow(clippy::unwrap_used, clippy::expect_used, clippy::panic, missing_docs)]

mod tokenize;
mod vendor_channel;
mod vendor_ring;
