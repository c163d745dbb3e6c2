//! SUMO FCD traces (`--fcd-output`) → a [`Log`], checked against the network they claim to run on.

use super::net::SumoNet;
use super::types::TypeTable;
use super::xml::{Item, XmlStream, input_error};
use crate::error::Result;
use crate::log::{Log, State, Track};
use std::collections::HashMap;
use std::f64::consts::FRAC_PI_2;
use std::path::Path;
use umgen_scene::{AgentCategory, wrap_angle};

/// How far outside the network boundary a position may lie before the trace is refused (m).
const BOUNDARY_MARGIN: f64 = 50.0;

/// A parsed trace.
#[derive(Debug)]
pub struct Fcd {
    /// The states.
    pub log: Log,
    /// Records of classes umgen does not model (rail, ships), left out.
    pub skipped: u64,
}

/// Parses an FCD file. Vehicle positions are SUMO's front-bumper centres and become box centres; SUMO
/// angles (degrees clockwise from north) become headings (radians counter-clockwise from east).
pub fn parse_fcd(path: &Path, net: &SumoNet, types: &TypeTable) -> Result<Fcd> {
    let mut xml = XmlStream::open(path)?;
    let mut tracks: Vec<Track> = Vec::new();
    let mut ids: HashMap<(bool, String), u32> = HashMap::new();
    let mut steps: Vec<Vec<State>> = Vec::new();
    let (mut times, mut skipped, mut root) = (Vec::<f64>::new(), 0u64, false);
    let b = net.boundary;
    while let Some(item) = xml.next()? {
        let Item::Open(el) = item else { continue };
        match el.name.as_str() {
            "fcd-export" => root = true,
            "timestep" => {
                let t = el.num("time", &xml)?;
                if let (Some(&t0), Some(&last)) = (times.first(), times.last()) {
                    let dt = times.get(1).map_or(t - last, |t1| t1 - t0);
                    let expected = t0 + dt * times.len() as f64;
                    if dt <= 0.0 || (t - expected).abs() > 1e-3 * dt.max(1e-3) {
                        return Err(xml.error(
                            &el,
                            format!("timestep {t} breaks the regular {dt} s spacing (expected {expected})"),
                        ));
                    }
                }
                times.push(t);
                steps.push(Vec::new());
            }
            "vehicle" | "person" => {
                let person = el.name == "person";
                let Some(step) = steps.last_mut() else {
                    return Err(xml.error(&el, format!("<{}> outside a <timestep>", el.name)));
                };
                let name = el.req("id", &xml)?;
                let type_id = el.req("type", &xml)?;
                let info = types.get(type_id).ok_or_else(|| {
                    xml.error(
                        &el,
                        format!(
                            "{} `{name}` has type `{type_id}`, which no --types file defines",
                            el.name
                        ),
                    )
                })?;
                let Some(category) = (if person {
                    Some(AgentCategory::Pedestrian)
                } else {
                    info.category
                }) else {
                    skipped += 1;
                    continue;
                };
                let place = if person {
                    ("edge", &net.edges)
                } else {
                    ("lane", &net.lanes)
                };
                if let Some(p) = el.get(place.0).filter(|p| !p.is_empty() && !place.1.contains(*p)) {
                    return Err(xml.error(&el, format!("{} `{name}` is on {} `{p}`, which the network does not have: the trace does not match the network", el.name, place.0)));
                }
                let (x, y) = (el.num("x", &xml)?, el.num("y", &xml)?);
                if x < b[0] - BOUNDARY_MARGIN
                    || x > b[2] + BOUNDARY_MARGIN
                    || y < b[1] - BOUNDARY_MARGIN
                    || y > b[3] + BOUNDARY_MARGIN
                {
                    return Err(xml.error(
                        &el,
                        format!(
                            "{} `{name}` at ({x}, {y}) lies outside the network's boundary {b:?}",
                            el.name
                        ),
                    ));
                }
                let heading = wrap_angle(FRAC_PI_2 - el.num("angle", &xml)?.to_radians());
                let speed = el.num("speed", &xml)?;
                let key = (person, name.to_string());
                let track = match ids.get(&key) {
                    Some(&t) => t,
                    None => {
                        let t = tracks.len() as u32;
                        tracks.push(Track {
                            name: name.into(),
                            category,
                            class: info.class.clone(),
                            length: info.length,
                            width: info.width,
                            height: info.height,
                        });
                        ids.insert(key, t);
                        t
                    }
                };
                if step.iter().any(|s| s.track == track) {
                    return Err(xml.error(&el, format!("{} `{name}` appears twice in one timestep", el.name)));
                }
                // SUMO places vehicles by their front bumper; umgen boxes are centred.
                let back = if person {
                    0.0
                } else {
                    tracks[track as usize].length / 2.0
                };
                let (cx, cy) = (x - back * heading.cos(), y - back * heading.sin());
                step.push(State {
                    track,
                    x: cx as f32,
                    y: cy as f32,
                    heading: heading as f32,
                    speed: speed as f32,
                });
            }
            _ => {}
        }
    }
    if !root {
        return Err(input_error(
            path,
            0,
            "not an FCD file: no <fcd-export> element".into(),
        ));
    }
    if times.len() < 2 {
        return Err(input_error(
            path,
            0,
            format!("{} timestep(s); a trace needs at least two", times.len()),
        ));
    }
    for s in &mut steps {
        s.sort_by_key(|x| x.track);
    }
    let dt = times[1] - times[0];
    Ok(Fcd {
        log: Log {
            tracks,
            t0: times[0],
            dt,
            steps,
        },
        skipped,
    })
}
