//! umgen checkpoints.
//!
//! A run's checkpoints live in one directory: `step-000000123/` per saved step, each with its files and a
//! `manifest.json` (kind, step, umgen version, free-form metadata, SHA-256 of every file), plus `latest`
//! naming the newest. [`CheckpointDir::save`] writes atomically (temporary directory, fsync, rename) and
//! keeps the newest K; [`CheckpointDir::load_latest`] verifies checksums and takes the highest step that
//! passes, or fails naming every checkpoint when none does. A resumed run moves damaged newer checkpoints
//! aside ([`CheckpointDir::set_aside_newer`]) rather than overwrite or prune for them, and removes what
//! interrupted saves left ([`CheckpointDir::remove_stale_temporaries`]).
//!
//! The [`burn_io`] functions turn burn modules into safetensors bytes (names = module paths) and optimizer
//! state into bytes, with parameter ids derived from paths so that a resumed process matches them, and
//! find non-finite weights ([`burn_io::first_non_finite`]) before a checkpoint or bundle holds them.

pub mod burn_io;
mod dir;
mod error;

pub use dir::{CheckpointDir, FileEntry, LATEST, Loaded, MANIFEST, Manifest, load, sha256};
pub use error::{CheckpointError, Result};
