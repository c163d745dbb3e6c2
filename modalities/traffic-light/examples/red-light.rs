//! Vehicles crossing stop lines on red: a split's recorded clips against `umgen generate` outputs.
//!
//! ```sh
//! cargo run --release -p umgen-modality-traffic-light --example red-light -- \
//!     --data data/sumo-sample --split test runs/gen-without-lights runs/gen-with-lights
//! ```
//!
//! For the recorded clips, every pair of consecutive frames of the split counts, with the lights SUMO
//! recorded. For a generated output, every pair of consecutive generated frames of every scene counts,
//! against the lights SUMO recorded at the same time of the context clip (`generate --recorded-ego` keeps
//! the ego on its recorded path, so those lights stand where the generated agents see them): all of them,
//! and the nearest to the ego that the modality tokenizes (the only ones a model with the modality is
//! shown, e.g. with `generate --recorded ego,lights`); a model with the traffic-light modality is also
//! measured against the lights it generated itself. Prints a Markdown
//! table: crossings, crossings on red (and of those, the ones made above 5 m/s: driven through, not crept
//! over while stopping), their share with its 95 % (Wilson) interval, red approaches (a vehicle within 20 m behind a red
//! line) and red crossings per approach; and for such a model, how its lights agree with SUMO's (the stop
//! lines of the 8 nearest recorded heads, a generated line at each, the same state).

use std::collections::HashMap;
use std::io::Write;
use std::path::{Path, PathBuf};
use umgen::data::Dataset;
use umgen::scene::{Frame, SceneClip};
use umgen_modality_traffic_light::crossings::{
    Agreement, Crossings, StopLine, THROUGH_MPS, crossings, stop_lines,
};
use umgen_modality_traffic_light::{TrafficLight, TrafficLightConfig};

type Error = Box<dyn std::error::Error>;

fn read_json(p: &Path) -> Result<serde_json::Value, Error> {
    let bytes = std::fs::read(p).map_err(|e| format!("{}: {e}", p.display()))?;
    Ok(serde_json::from_slice(&bytes).map_err(|e| format!("{}: {e}", p.display()))?)
}

/// Crossings from `prev` to `next` against the lines of `lights` (a frame whose heads and ego pose
/// place them).
fn step(lights: &TrafficLight, at: &Frame, prev: &Frame, next: &Frame) -> Result<Crossings, Error> {
    let lines = stop_lines(&lights.heads(at, 0)?, &at.ego.pose2());
    Ok(crossings(prev, next, &lines))
}

fn recorded(lights: &TrafficLight, data: &Path, split: &str) -> Result<(Crossings, usize), Error> {
    let ds = Dataset::open(data)?;
    let mut total = Crossings::default();
    let mut pairs = 0;
    for (i, clip) in ds.clips().iter().enumerate().filter(|(_, c)| c.split == split) {
        let frames = ds.read_window(i, 0, clip.frames, 1)?.frames;
        for w in frames.windows(2) {
            total.add(&step(lights, &w[0], &w[0], &w[1])?);
            pairs += 1;
        }
    }
    Ok((total, pairs))
}

/// What one `umgen generate` output measures: crossings against SUMO's lights, all of them and the
/// nearest ones that the modality tokenizes; for a model with lights, crossings against its own and how
/// its lights agree with SUMO's; the frame pairs.
struct Generated {
    sumo: Crossings,
    nearest: Crossings,
    own: Option<(Crossings, Agreement)>,
    pairs: usize,
}

/// The stop lines of the `count` heads nearest to the ego of `frame` (what the modality tokenizes).
fn nearest_lines(lights: &TrafficLight, frame: &Frame) -> Result<Vec<StopLine>, Error> {
    let mut heads = lights.heads(frame, 0)?;
    heads.truncate(lights.config().count);
    Ok(stop_lines(&heads, &frame.ego.pose2()))
}

/// Against SUMO's lights, and against the scene's own lights when it has them.
fn generated(lights: &TrafficLight, dir: &Path) -> Result<Generated, Error> {
    let meta = read_json(&dir.join("meta.json"))?;
    let tokens = read_json(&dir.join("tokens.json"))?;
    let scenes: Vec<SceneClip> = serde_json::from_value(read_json(&dir.join("scenes.json"))?)?;
    let mut opened: HashMap<String, Dataset> = HashMap::new();
    let (mut sumo, mut nearest, mut own, mut pairs) = (
        Crossings::default(),
        Crossings::default(),
        Crossings::default(),
        0,
    );
    let mut agree = Agreement::default();
    // A model with the modality decodes its lights into every frame; one without has none.
    let key = &lights.config().key;
    let has_own = scenes
        .iter()
        .flat_map(|s| s.frames.first())
        .all(|f| f.extras.contains_key(key));
    for (s, scene) in scenes.iter().enumerate() {
        let c = tokens["context_of"][s]
            .as_u64()
            .ok_or("tokens.json: context_of")? as usize;
        let context = &meta["contexts"][c];
        let data = context["data"].as_str().ok_or("meta.json: contexts[].data")?;
        let n = context["frames"].as_u64().ok_or("meta.json: contexts[].frames")? as usize;
        if !opened.contains_key(data) {
            opened.insert(data.to_string(), Dataset::open(Path::new(data))?);
        }
        let ds = &opened[data];
        let index = ds.find_clip(context["clip"].as_str().ok_or("meta.json: contexts[].clip")?)?;
        // Generated frames beyond the recorded clip have no recorded lights.
        let g = scene.frames.len().min(ds.clips()[index].frames - n);
        let real = ds.read_window(index, 0, n + g, 1)?.frames;
        for k in 1..g {
            let (prev, next) = (&scene.frames[k - 1], &scene.frames[k]);
            let at = &real[n + k - 1];
            sumo.add(&step(lights, at, prev, next)?);
            nearest.add(&crossings(prev, next, &nearest_lines(lights, at)?));
            if has_own {
                own.add(&step(lights, prev, prev, next)?);
                agree.add(
                    &nearest_lines(lights, &real[n + k - 1])?,
                    &nearest_lines(lights, prev)?,
                );
            }
            pairs += 1;
        }
    }
    Ok(Generated {
        sumo,
        nearest,
        own: has_own.then_some((own, agree)),
        pairs,
    })
}

fn row(name: &str, c: &Crossings, pairs: usize) -> String {
    let pct = |v: Option<f64>| v.map_or("–".into(), |v| format!("{:.1} %", 100.0 * v));
    let interval = c.red_share_interval().map_or("–".into(), |(lo, hi)| {
        format!("{:.1}–{:.1} %", 100.0 * lo, 100.0 * hi)
    });
    format!(
        "| {name} | {pairs} | {} | {} | {} | {} ({interval}) | {} | {} |",
        c.total(),
        c.red,
        c.red_through,
        pct(c.red_share()),
        c.red_approaches,
        pct(c.run_rate())
    )
}

fn main() -> Result<(), Error> {
    let mut args = std::env::args().skip(1);
    let (mut data, mut split, mut dirs) = (None, "test".to_string(), Vec::new());
    while let Some(a) = args.next() {
        match a.as_str() {
            "--data" => data = Some(PathBuf::from(args.next().ok_or("--data DIR")?)),
            "--split" => split = args.next().ok_or("--split NAME")?,
            _ => dirs.push(PathBuf::from(a)),
        }
    }
    let data = data.ok_or("usage: red-light --data DIR [--split NAME] [GENERATED_DIR ...]")?;
    let lights = TrafficLight::new("lights", TrafficLightConfig::default())?;
    let mut out = std::io::stdout().lock();
    writeln!(
        out,
        "| frames of | frame pairs | crossings | on red | on red above {THROUGH_MPS} m/s | share on red (95 % interval) | red approaches | red run per approach |"
    )?;
    writeln!(out, "|---|---|---|---|---|---|---|---|")?;
    let (c, pairs) = recorded(&lights, &data, &split)?;
    writeln!(out, "{}", row(&format!("recorded `{split}`"), &c, pairs))?;
    let mut agreements = Vec::new();
    for dir in &dirs {
        let g = generated(&lights, dir)?;
        let name = dir.display();
        writeln!(
            out,
            "{}",
            row(&format!("{name} (SUMO's lights)"), &g.sumo, g.pairs)
        )?;
        let nearest = format!("{name} (SUMO's {} nearest heads)", lights.config().count);
        writeln!(out, "{}", row(&nearest, &g.nearest, g.pairs))?;
        if let Some((own, agree)) = g.own {
            writeln!(out, "{}", row(&format!("{name} (its own lights)"), &own, g.pairs))?;
            agreements.push((name, agree));
        }
    }
    if !agreements.is_empty() {
        writeln!(out)?;
        writeln!(
            out,
            "| generated lights of | SUMO's stop lines | with a generated line there | same state |"
        )?;
        writeln!(out, "|---|---|---|---|")?;
        for (name, a) in agreements {
            let pct = |n: u64, of: u64| 100.0 * n as f64 / of.max(1) as f64;
            writeln!(
                out,
                "| {name} | {} | {} ({:.1} %) | {} ({:.1} %) |",
                a.lines,
                a.matched,
                pct(a.matched, a.lines),
                a.same_state,
                pct(a.same_state, a.matched)
            )?;
        }
    }
    Ok(())
}
