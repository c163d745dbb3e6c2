//! The commands as a library: an `App` with a user's modality kind runs the stock commands on a config that
//! uses it; the stock binary refuses that config, naming the kind; a kind registered twice is refused.
#![allow(clippy::unwrap_used, clippy::expect_used, clippy::panic, missing_docs)]

mod common;
use common::{text, umgen};

use std::process::ExitCode;
use std::sync::Arc;
use umgen::modality::{DecodeReport, Modality, ModalitySpec, Result};
use umgen::scene::{Frame, SceneClip};
use umgen_cli::App;

/// A user's modality kind, as small as one can be: one token per frame, whether the ego moves.
#[derive(Debug)]
struct Moving(ModalitySpec);

impl Moving {
    fn factory(name: &str, _: &toml::Table) -> Result<Arc<dyn Modality>> {
        Ok(Arc::new(Moving(ModalitySpec::new(name, "moving", 2, 1))))
    }
}

impl Modality for Moving {
    fn spec(&self) -> &ModalitySpec {
        &self.0
    }
    fn tokenize(&self, clip: &SceneClip, t: usize) -> Result<Vec<u32>> {
        Ok(vec![u32::from(clip.frame(t)?.ego.speed > 0.1)])
    }
    fn detokenize(&self, ids: &[u32], frame: &mut Frame) -> Result<DecodeReport> {
        frame.ego.speed = f64::from(ids[0]);
        Ok(DecodeReport::default())
    }
}

fn moving_config(dir: &std::path::Path) -> std::path::PathBuf {
    let p = dir.join("moving.toml");
    let text = "[layout]\norder = [\"ego\", \"moving\"]\n[backbone]\nalign = \"\"\n";
    std::fs::write(&p, text).unwrap();
    p
}

#[test]
fn an_app_runs_the_commands_with_a_users_modality_kind() {
    let dir = tempfile::tempdir().unwrap();
    let cfg = moving_config(dir.path());
    let cfg = cfg.to_str().unwrap();
    let app = App::new().modality("moving", Moving::factory);
    assert_eq!(
        app.run_from(["umgen", "layout", "--config", cfg, "--json"]),
        ExitCode::SUCCESS
    );
    // The stock binary does not know the kind and says which.
    let out = umgen(&["layout", "--config", cfg]);
    assert!(!out.status.success());
    let err = text(&out.stderr);
    assert!(err.contains("unknown kind `moving`"), "{err}");
    // A kind that is already built in cannot be registered again.
    let twice = App::new().modality("agent", Moving::factory);
    assert_eq!(
        twice.run_from(["umgen", "layout", "--config", cfg]),
        ExitCode::FAILURE
    );
}
