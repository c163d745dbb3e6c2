//! Small datasets for integration tests, imported through the real SUMO importer.

use std::ops::ControlFlow;
use std::path::{Path, PathBuf};
use umgen::data::Dataset;
use umgen::data::sumo::{ImportOptions, import};
use umgen::{DatasetRasters, UmgenConfig, vq_target};

/// The hand-made SUMO network of the data crate's tests (a two-way road into a traffic light).
pub fn tiny_net() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../crates/data/tests/fixtures/tiny.net.xml")
}

/// An FCD trace of `steps` steps on [`tiny_net`]: two cars driving east on lane AB_0 at 2 m/s, 10 m
/// apart (slow enough to stay on the 100 m road for 40 steps), and a pedestrian on the sidewalk.
pub fn fcd_text(steps: usize) -> String {
    let mut s = String::from("<?xml version=\"1.0\"?>\n<fcd-export>\n");
    for i in 0..steps {
        let t = i as f64 * 0.5;
        s += &format!("    <timestep time=\"{t:.2}\">\n");
        for (id, x0) in [("ego", 22.5), ("lead", 32.5)] {
            s += &format!(
                "        <vehicle id=\"{id}\" x=\"{:.2}\" y=\"-4.80\" angle=\"90.00\" type=\"DEFAULT_VEHTYPE\" speed=\"2.00\" lane=\"AB_0\"/>\n",
                x0 + 2.0 * t
            );
        }
        s += &format!(
            "        <person id=\"walker\" x=\"{:.2}\" y=\"-7.40\" angle=\"90.00\" type=\"DEFAULT_PEDTYPE\" speed=\"1.00\" edge=\"SW\"/>\n",
            30.0 + t
        );
        s += "    </timestep>\n";
    }
    s + "</fcd-export>\n"
}

/// Imports a `steps`-step trace on the tiny network into `dir/ds` as clips of up to 6 frames; returns the
/// dataset directory.
pub fn tiny_dataset(dir: &Path, steps: usize) -> std::io::Result<PathBuf> {
    let fcd = dir.join("run.fcd.xml");
    std::fs::write(&fcd, fcd_text(steps))?;
    let mut o = ImportOptions::new(tiny_net(), fcd, dir.join("ds"));
    (o.min_frames, o.clip_frames) = (3, 6);
    import(&o).map_err(|e| std::io::Error::other(e.to_string()))?;
    Ok(dir.join("ds"))
}

/// Trains the map and image tokenizers of `config` on every frame of `data` into `out/map` and
/// `out/image`, for as many steps as the config's `vq_train` says (tests use two: enough to exercise the
/// pipeline, not to reconstruct well). The configured tokenizer paths are ignored.
pub fn train_tokenizers(config: &UmgenConfig, data: &Dataset, out: &Path) -> umgen::Result<()> {
    for m in ["map", "image"] {
        let target = vq_target(config, m)?;
        let source = DatasetRasters::new(data, target.view.as_ref(), None, 1);
        umgen::tokenizer_vq::train::<burn::backend::Autodiff<burn::backend::Flex>>(
            &target.vq,
            &target.train,
            &source,
            &out.join(m),
            &Default::default(),
            |_| ControlFlow::Continue(()),
        )?;
    }
    Ok(())
}
