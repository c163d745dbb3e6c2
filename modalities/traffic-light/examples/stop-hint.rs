//! Whether the follow hint's braking agrees with SUMO's vehicles, on recorded token windows: each frame's
//! tracked slots moved one frame ahead (burn's `backbone::track::moved`, the hint a model is trained
//! with) without the follow rule, with it, and with it and the lights' stop points, against the same
//! slot in the recorded next frame.
//!
//! ```sh
//! cargo run --release -p umgen-modality-traffic-light --example stop-hint -- \
//!     --config modalities/traffic-light/configs/small-bundled-lights.toml --tokens runs/sblm/tokens
//! ```
//!
//! For the slots that a rule brakes (their hinted speed below the hint without it), it prints how many
//! there are, how often the recorded next speed is nearer the braked hint than the unbraked one, and
//! the mean speeds, over all of them and by how hard the rule brakes: a rule whose braking the data
//! does not follow teaches a model to depart from it.
//! The token cache must be made for the config's layout (`umgen-lights tokenize`).

use burn::tensor::{Int, Tensor, TensorData};
use std::io::Write;
use std::path::PathBuf;
use umgen::UmgenConfig;
use umgen::backbone::TrackSpec;
use umgen::backbone::track::moved;
use umgen::data::TokenSet;
use umgen_modality_traffic_light::{KIND, TrafficLight};

type Error = Box<dyn std::error::Error>;
type F = burn::backend::Flex;

/// Lower ends (m/s²) of the classes of how hard a rule brakes.
const CLASSES: [f64; 4] = [0.0, 2.0, 4.0, 6.0];

/// Slots a rule braked and how the recorded next frame compares.
#[derive(Default, Clone)]
struct Braked {
    slots: usize,
    nearer_braked: usize,
    hint: f64,
    braked: f64,
    recorded: f64,
}

impl Braked {
    fn add(&mut self, unbraked: f64, braked: f64, recorded: f64) {
        self.slots += 1;
        self.nearer_braked += usize::from((recorded - braked).abs() < (recorded - unbraked).abs());
        self.hint += unbraked;
        self.braked += braked;
        self.recorded += recorded;
    }

    fn row(&self, name: &str) -> String {
        let n = self.slots.max(1) as f64;
        format!(
            "| {name} | {} | {:.1} % | {:.2} | {:.2} | {:.2} |",
            self.slots,
            100.0 * self.nearer_braked as f64 / n,
            self.hint / n,
            self.braked / n,
            self.recorded / n
        )
    }
}

/// Each slot's speed (m/s, from the bin centres of vx and vy) in `ids` `[slots · k]`; `None` for an
/// empty slot.
fn speeds(ids: &[i64], spec: &TrackSpec) -> Vec<Option<f64>> {
    let centre = |f: usize, id: i64| {
        let (lo, hi, bins) = spec.fields[f].1;
        lo + (id as f64 + 0.5) * (hi - lo) / f64::from(bins)
    };
    ids.chunks(spec.slot)
        .map(|s| {
            (s[spec.fields[0].0] < spec.values as i64)
                .then(|| centre(2, s[spec.fields[2].0]).hypot(centre(3, s[spec.fields[3].0])))
        })
        .collect()
}

fn main() -> Result<(), Error> {
    let mut args = std::env::args().skip(1);
    let (mut config, mut tokens, mut limit) = (None, None, 20_000usize);
    while let Some(a) = args.next() {
        match a.as_str() {
            "--config" => config = Some(PathBuf::from(args.next().ok_or("--config FILE")?)),
            "--tokens" => tokens = Some(PathBuf::from(args.next().ok_or("--tokens DIR")?)),
            "--windows" => limit = args.next().ok_or("--windows N")?.parse()?,
            _ => return Err(format!("unknown argument `{a}`").into()),
        }
    }
    let usage = "usage: stop-hint --config FILE --tokens DIR [--windows N]";
    let (config, tokens) = (config.ok_or(usage)?, tokens.ok_or(usage)?);
    let text = std::fs::read_to_string(&config).map_err(|e| format!("{}: {e}", config.display()))?;
    let mut cfg = UmgenConfig::from_toml_str(&text)?;
    let lights = cfg
        .layout
        .order
        .iter()
        .find(|n| {
            cfg.modality
                .get(*n)
                .and_then(|t| t.get("kind"))
                .and_then(|k| k.as_str())
                == Some(KIND)
        })
        .cloned()
        .ok_or_else(|| format!("{}: no modality of kind `{KIND}`", config.display()))?;
    cfg.backbone.track_follow = true;
    cfg.backbone.track_stops = Some(lights);
    let mut catalog = umgen::builtin_catalog()?;
    catalog.add(KIND, TrafficLight::factory)?;
    let registry = cfg.registry(&catalog)?;
    let spec = umgen::backbone_spec(&registry, &cfg.backbone)?;
    let layout = registry.layout()?;
    let set = TokenSet::open(&tokens, layout.fingerprint())?;
    let (Some(track), Some(action)) = (spec.track.clone(), spec.action.clone()) else {
        return Err("the config tracks no slots (backbone.track) or has no action".into());
    };
    let (seg, ego) = (&spec.segments[track.segment], &spec.segments[action.segment]);
    let stops = track
        .stops
        .as_ref()
        .map(|s| &spec.segments[s.segment])
        .ok_or("no stop points")?;
    let variants = [
        TrackSpec {
            follow: None,
            stops: None,
            ..track.clone()
        },
        TrackSpec {
            stops: None,
            ..track.clone()
        },
        track.clone(),
    ];
    let mut windows = set.windows(2, 1, None);
    // An even spread over the cache when it holds more windows than asked for.
    let step = (windows.len() / limit.max(1)).max(1);
    windows = windows.into_iter().step_by(step).take(limit).collect();
    let n = layout.len();
    // [all, by class] for the follow rule and the stop points.
    let mut follow = vec![Braked::default(); CLASSES.len() + 1];
    let mut stop = follow.clone();
    let add = |to: &mut Vec<Braked>, a: f64, b: f64, r: f64| {
        let hard = (a - b) / track.step_s;
        let class = CLASSES.iter().rposition(|&lo| hard >= lo).unwrap_or(0);
        to[0].add(a, b, r);
        to[class + 1].add(a, b, r);
    };
    let dev = Default::default();
    for batch in windows.chunks(512) {
        let mut now = Vec::with_capacity(batch.len() * n);
        let mut next = Vec::with_capacity(batch.len() * n);
        for w in batch {
            let rows = set.read(*w, 2, 1)?;
            now.extend(rows[..n].iter().map(|&t| i64::from(t)));
            next.extend(rows[n..].iter().map(|&t| i64::from(t)));
        }
        let b = batch.len();
        let frame = Tensor::<F, 3, Int>::from_data(TensorData::new(now, [b, 1, n]), &dev);
        let act: Vec<f32> = next
            .chunks(n)
            .flat_map(|r| {
                (0..3)
                    .map(|k| action.decode(k, r[ego.offset + k] as u32) as f32)
                    .collect::<Vec<_>>()
            })
            .collect();
        let act = Tensor::<F, 3>::from_data(TensorData::new(act, [b, 1, 3]), &dev);
        let slots = frame.clone().narrow(2, seg.offset, seg.tokens);
        let heads = frame.narrow(2, stops.offset, stops.tokens);
        let hinted: Vec<Vec<i64>> = variants
            .iter()
            .map(|v| {
                moved(slots.clone(), Some(heads.clone()), act.clone(), v)
                    .into_data()
                    .iter::<i64>()
                    .collect()
            })
            .collect();
        for (i, rec) in next.chunks(n).enumerate() {
            let at = |h: &Vec<i64>| speeds(&h[i * seg.tokens..(i + 1) * seg.tokens], &track);
            let [none, fol, stp] = [at(&hinted[0]), at(&hinted[1]), at(&hinted[2])];
            let real = speeds(&rec[seg.offset..seg.offset + seg.tokens], &track);
            for j in 0..real.len() {
                let (Some(a), Some(f), Some(s), Some(r)) = (none[j], fol[j], stp[j], real[j]) else {
                    continue;
                };
                if f < a - 1e-9 {
                    add(&mut follow, a, f, r);
                }
                if s < f - 1e-9 {
                    add(&mut stop, f, s, r);
                }
            }
        }
    }
    let mut out = std::io::stdout().lock();
    writeln!(out, "{} frame pairs of {}", windows.len(), tokens.display())?;
    writeln!(
        out,
        "| braked by | slots | recorded nearer the braked hint | hint without the rule m/s | braked hint m/s | recorded m/s |"
    )?;
    writeln!(out, "|---|---|---|---|---|---|")?;
    for (name, rows) in [
        ("the follow rule (slots ahead)", &follow),
        ("the stop points (red heads), beyond the follow rule", &stop),
    ] {
        writeln!(out, "{}", rows[0].row(name))?;
        for (i, lo) in CLASSES.iter().enumerate() {
            let class = match CLASSES.get(i + 1) {
                Some(hi) => format!("{lo}–{hi} m/s²"),
                None => format!("{lo} m/s² and more"),
            };
            writeln!(out, "{}", rows[i + 1].row(&format!("… braking {class}")))?;
        }
    }
    Ok(())
}
