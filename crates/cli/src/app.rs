//! The `umgen` commands with more modality kinds: a user's crate registers its kinds and gets every command
//! (`train`, `export`, `generate`, `eval`, `viz`, `layout`, …) with them, without copying the CLI:
//!
//! ```no_run
//! # fn factory(name: &str, t: &toml::Table) -> umgen::modality::Result<std::sync::Arc<dyn umgen::modality::Modality>> { todo!() }
//! fn main() -> std::process::ExitCode {
//!     umgen_cli::App::new().modality("traffic_light", factory).run()
//! }
//! ```
//!
//! A bundle's manifest records each modality's kind (`layout.segments[*].kind`); a binary that lacks one of
//! them refuses the bundle, naming it.

use crate::cli::Cli;
use clap::Parser;
use std::ffi::OsString;
use std::io::Write;
use std::process::ExitCode;
use std::sync::Arc;
use umgen::modality::{Modality, ModalityCatalog, Result as ModalityResult};
use umgen::tokenizer_vq::CodecLoader;

/// A modality factory: the modality named `name` from its `[modality.<name>]` table.
type Factory = dyn Fn(&str, &toml::Table) -> ModalityResult<Arc<dyn Modality>> + Send + Sync;

/// The modality kinds a binary knows beyond the built-in ones (`ego`, `map`, `agent`, `image`).
#[derive(Clone, Default)]
pub struct Kinds {
    extra: Vec<(String, Arc<Factory>)>,
}

impl std::fmt::Debug for Kinds {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_list().entries(self.extra.iter().map(|(k, _)| k)).finish()
    }
}

impl Kinds {
    /// The built-in catalog (VQ tokenizers on the CPU) with these kinds added.
    pub fn catalog(&self) -> ModalityResult<ModalityCatalog> {
        self.catalog_with(umgen::tokenizer_vq::cpu_loader())
    }

    /// The built-in catalog with VQ tokenizers loaded by `loader`, with these kinds added; a kind that is
    /// already there is refused, naming it.
    pub fn catalog_with(&self, loader: CodecLoader) -> ModalityResult<ModalityCatalog> {
        let mut catalog = umgen::builtin_catalog_with(loader)?;
        for (kind, factory) in &self.extra {
            let factory = Arc::clone(factory);
            catalog.add(kind, move |name: &str, table: &toml::Table| factory(name, table))?;
        }
        Ok(catalog)
    }
}

/// The `umgen` command line, with the modality kinds registered on it.
#[derive(Debug, Default)]
pub struct App {
    kinds: Kinds,
}

impl App {
    /// The stock commands and modality kinds.
    pub fn new() -> Self {
        Self::default()
    }

    /// Adds the modality kind `kind`, built by `factory` from a modality's name and config table.
    pub fn modality<F>(mut self, kind: &str, factory: F) -> Self
    where
        F: Fn(&str, &toml::Table) -> ModalityResult<Arc<dyn Modality>> + Send + Sync + 'static,
    {
        self.kinds.extra.push((kind.to_string(), Arc::new(factory)));
        self
    }

    /// Parses the process's arguments and runs the command: the exit code, errors on stderr.
    pub fn run(self) -> ExitCode {
        self.run_from(std::env::args_os())
    }

    /// [`run`](Self::run) with the arguments given (the first is the program's name).
    pub fn run_from<I, T>(self, args: I) -> ExitCode
    where
        I: IntoIterator<Item = T>,
        T: Into<OsString> + Clone,
    {
        let args = Cli::parse_from(args);
        run_main(args.verbose, || {
            crate::commands::guard_parent();
            crate::commands::run(args.command, &self.kinds)
        })
    }
}

/// The `main` of `umgen` and of the developer tools built on it: sets up logging (`verbose`), the CUDA
/// kernel cache and memory pool, runs `command`, and turns its error into one line on stderr and a failing
/// exit code.
pub fn run_main(verbose: u8, command: impl FnOnce() -> anyhow::Result<()>) -> ExitCode {
    crate::logging::init(verbose);
    #[cfg(feature = "cuda")]
    if let Some(dir) = crate::device::init_kernel_cache() {
        tracing::debug!("compiled CUDA kernels are kept in {}", dir.display());
    }
    #[cfg(feature = "cuda")]
    let command = || {
        let layout = crate::memory_pool::init()?;
        tracing::debug!("CUDA memory pool: {layout}");
        command()
    };
    match command() {
        Ok(()) => ExitCode::SUCCESS,
        Err(err) => {
            // The whole cause chain on one line; nothing else to do if stderr is gone.
            let _ = writeln!(std::io::stderr(), "error: {err:#}");
            ExitCode::FAILURE
        }
    }
}
