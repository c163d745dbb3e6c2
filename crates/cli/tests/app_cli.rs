//! The commands as a library: an `App` with a user's modality kind runs the stock commands on a config that
//! uses it; the stock binary refuses that config, naming the kind; a kind registered twice is refused.
#![allow(clippy::unwrap_used, clippy::expect_used, clippy::panic, missing_docs)]

mod common;
use common::{text, umgen};

use std::process::ExitCode;
use umgen_cli::App;
use umgen_tests::traffic_lights::{self, TrafficLights};

fn lights_config(dir: &std::path::Path) -> std::path::PathBuf {
    let p = dir.join("lights.toml");
    let text = "[layout]\norder = [\"ego\", \"lights\"]\n[modality.lights]\nkind = \"traffic_lights\"\ncount = 3\n[backbone]\nalign = \"\"\n";
    std::fs::write(&p, text).unwrap();
    p
}

#[test]
fn an_app_runs_the_commands_with_a_users_modality_kind() {
    let dir = tempfile::tempdir().unwrap();
    let cfg = lights_config(dir.path());
    let cfg = cfg.to_str().unwrap();
    let app = App::new().modality(traffic_lights::KIND, TrafficLights::factory);
    assert_eq!(
        app.run_from(["umgen", "layout", "--config", cfg, "--json"]),
        ExitCode::SUCCESS
    );
    // The stock binary does not know the kind and says which.
    let out = umgen(&["layout", "--config", cfg]);
    assert!(!out.status.success());
    let err = text(&out.stderr);
    assert!(err.contains("unknown kind `traffic_lights`"), "{err}");
    // A kind that is already built in cannot be registered again.
    let twice = App::new().modality("agent", TrafficLights::factory);
    assert_eq!(
        twice.run_from(["umgen", "layout", "--config", cfg]),
        ExitCode::FAILURE
    );
}
