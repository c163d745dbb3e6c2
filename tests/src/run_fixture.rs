//! A tiny imported SUMO dataset with trained (2-step) tokenizers and a config per run directory: the
//! fixture of the end-to-end CLI tests (train, export, generate, eval).

use crate::fixtures::{tiny_dataset, train_tokenizers};
use std::path::{Path, PathBuf};
use umgen::UmgenConfig;
use umgen::data::Dataset;

/// The fixture's config: tiny tokenizers (trained here for two steps) and a tiny backbone.
pub fn config_text(dir: &Path, data: &Path, out: &str, steps: u64) -> String {
    let tok = |m: &str| dir.join("tok").join(m).display().to_string();
    format!(
        "[layout]\norder = [\"ego\", \"map\", \"agent\", \"image\"]\n\
         [modality.agent]\nmax_agents = 4\n\
         [modality.map]\nraster = [32, 32]\ngrid = [4, 4]\ncodebook_size = 32\ntokenizer = \"{}\"\n\
         [modality.map.vq]\nbase = 8\nmult = [1, 2, 2, 2]\nres_blocks = 1\nz_channels = 4\nembed_dim = 4\nattention = false\ngroups = 4\n\
         [modality.map.vq_train]\nsteps = 2\nbatch_size = 2\nthreads = 1\n\
         [modality.image]\nsize = [32, 64]\ngrid = [2, 4]\ncodebook_size = 32\ntokenizer = \"{}\"\n\
         [modality.image.vq]\nbase = 8\nmult = [1, 1, 2, 2, 2]\nres_blocks = 1\nz_channels = 4\nembed_dim = 4\nattention = false\ngroups = 4\n\
         [modality.image.vq_train]\nsteps = 2\nbatch_size = 2\nthreads = 1\n\
         [backbone]\nd_model = 32\nheads = 2\nmlp_ratio = 2\ndropout = 0.1\nego_hist_layers = 1\nego_env_layers = 1\ntar_layers = 1\noar_layers = 1\nmax_frames = 4\n\
         [train]\nout_dir = \"{}\"\ntokens = \"{}\"\ndata = \"{}\"\nsteps = {steps}\nbatch_size = 2\nframes = 2\nlr = 3e-3\nwarmup = 3\nlog_every = 1\ncheckpoint_every = 5\nkeep_checkpoints = 3\n",
        tok("map"),
        tok("image"),
        dir.join(out).display(),
        dir.join("tokens").display(),
        data.display()
    )
}

/// A fixture dataset, its tokenizers, and a config file per run directory name.
pub struct Fixture {
    /// The temporary directory holding everything.
    pub dir: tempfile::TempDir,
    /// The dataset.
    pub data: PathBuf,
}

impl Fixture {
    /// Imports the dataset into a temporary directory and trains the tokenizers.
    pub fn new() -> Result<Self, Box<dyn std::error::Error>> {
        let dir = tempfile::tempdir()?;
        let data = tiny_dataset(dir.path(), 40)?;
        let ds = Dataset::open(&data)?;
        let bare = UmgenConfig::from_toml_str(&config_text(dir.path(), &data, "unused", 1))?;
        train_tokenizers(&bare, &ds, &dir.path().join("tok"))?;
        Ok(Self { dir, data })
    }

    /// Writes `<run>.toml` for a run of `steps` steps into `<dir>/<run>`.
    pub fn config(&self, run: &str, steps: u64) -> std::io::Result<PathBuf> {
        let p = self.dir.path().join(format!("{run}.toml"));
        std::fs::write(&p, config_text(self.dir.path(), &self.data, run, steps))?;
        Ok(p)
    }

    /// The run directory of `run`.
    pub fn run_dir(&self, run: &str) -> PathBuf {
        self.dir.path().join(run)
    }
}
