//! `umgen-lights`: every `umgen` command, with the `traffic_light` modality kind registered.

use std::process::ExitCode;
use umgen_modality_traffic_light::{KIND, TrafficLight};

fn main() -> ExitCode {
    umgen_cli::App::new().modality(KIND, TrafficLight::factory).run()
}
