//! The commands as a library: an `App` with a user's modality kind runs the stock commands on a config that
//! uses it, and trains, exports and generates with it; the stock binary refuses that config and that
//! bundle, naming the kind; a kind registered twice is refused.
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

/// A config that trains the two-modality model on `data` for two steps into `dir/run`.
fn moving_training(dir: &std::path::Path, data: &std::path::Path) -> std::path::PathBuf {
    let p = dir.join("train.toml");
    let text = format!(
        "[layout]\norder = [\"ego\", \"moving\"]\n\
         [backbone]\nalign = \"\"\nd_model = 16\nheads = 2\nmlp_ratio = 2\nego_hist_layers = 1\n\
         ego_env_layers = 1\ntar_layers = 1\noar_layers = 1\nmax_frames = 4\n\
         [train]\nout_dir = \"{}\"\ntokens = \"{}\"\ndata = \"{}\"\nsteps = 2\nbatch_size = 2\nframes = 2\n",
        dir.join("run").display(),
        dir.join("tokens").display(),
        data.display()
    );
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

#[test]
fn the_stock_generate_refuses_a_bundle_of_a_users_kind_naming_it() {
    let dir = tempfile::tempdir().unwrap();
    let data = umgen_tests::fixtures::tiny_dataset(dir.path(), 30).unwrap();
    let cfg = moving_training(dir.path(), &data);
    let app = || App::new().modality("moving", Moving::factory);
    let (run, bundle) = (dir.path().join("run"), dir.path().join("bundle"));
    let arg = |p: &std::path::Path| p.to_str().unwrap().to_string();
    let train = ["umgen", "train", "--config", &arg(&cfg)].map(String::from);
    assert_eq!(app().run_from(train), ExitCode::SUCCESS);
    let export = [
        "umgen",
        "export",
        "--checkpoint",
        &arg(&run),
        "--out",
        &arg(&bundle),
    ]
    .map(String::from);
    assert_eq!(app().run_from(export), ExitCode::SUCCESS);
    let generate = |out: &str| {
        let out = arg(&dir.path().join(out));
        [
            "generate",
            "--bundle",
            &arg(&bundle),
            "--from-scratch",
            "--frames",
            "1",
            "--out",
            &out,
        ]
        .map(String::from)
    };
    // The user's binary generates with it; the stock one refuses, naming the kind it lacks.
    let with_kind = std::iter::once("umgen".to_string()).chain(generate("gen"));
    assert_eq!(app().run_from(with_kind), ExitCode::SUCCESS);
    assert!(dir.path().join("gen/tokens.json").exists());
    let args = generate("gen-stock");
    let out = umgen(&args.iter().map(String::as_str).collect::<Vec<_>>());
    assert!(!out.status.success());
    let err = text(&out.stderr);
    assert!(err.contains("unknown kind `moving`"), "{err}");
    assert!(!dir.path().join("gen-stock").exists());
}
