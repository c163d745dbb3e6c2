//! Dataset format, SUMO import and window reading, against hand-computed cases.
#![allow(clippy::unwrap_used, clippy::expect_used, clippy::panic, missing_docs)]

mod format;
mod geometry;
mod import;
mod scenes;
mod signals;

use std::path::{Path, PathBuf};

pub fn fixture(name: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("tests/fixtures")
        .join(name)
}

/// An FCD trace on the fixture network: `ego` and `lead` (10 m ahead of it) drive east on lane AB_0 at
/// 10 m/s, a pedestrian walks east on the sidewalk. SUMO positions vehicles by their front bumper.
pub fn fcd_text(steps: usize, lane: &str) -> String {
    let mut s = String::from("<?xml version=\"1.0\"?>\n<fcd-export>\n");
    for i in 0..steps {
        let t = i as f64 * 0.5;
        s += &format!("    <timestep time=\"{t:.2}\">\n");
        s += &format!(
            "        <vehicle id=\"ego\" x=\"{:.2}\" y=\"-4.80\" angle=\"90.00\" type=\"DEFAULT_VEHTYPE\" speed=\"10.00\" pos=\"1\" lane=\"{lane}\" slope=\"0.00\"/>\n",
            22.5 + 10.0 * t
        );
        s += &format!(
            "        <vehicle id=\"lead\" x=\"{:.2}\" y=\"-4.80\" angle=\"90.00\" type=\"DEFAULT_VEHTYPE\" speed=\"10.00\" pos=\"1\" lane=\"AB_0\" slope=\"0.00\"/>\n",
            32.5 + 10.0 * t
        );
        s += &format!(
            "        <person id=\"walker\" x=\"{:.2}\" y=\"-7.40\" angle=\"90.00\" type=\"DEFAULT_PEDTYPE\" speed=\"1.00\" pos=\"1\" edge=\"SW\" slope=\"0.00\"/>\n",
            30.0 + t
        );
        s += "    </timestep>\n";
    }
    s + "</fcd-export>\n"
}

pub fn write(dir: &Path, name: &str, text: &str) -> PathBuf {
    let p = dir.join(name);
    std::fs::write(&p, text).unwrap();
    p
}
