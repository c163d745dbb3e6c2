//! SUMO's traffic lights as [`Signals`]: each controlled vehicle connection of a `net.xml` (`<connection tl=
//! linkIndex=>` from a normal edge) is a signal head at the end of the lane it leaves, and the output of SUMO's
//! `SaveTLSStates` (`<tlsState time= id= state=>`, one character per link index, written every step) gives
//! each head's state over the log's steps.

use super::xml::{Item, XmlStream};
use crate::error::Result;
use crate::signals::{LightState, SignalHead, Signals};
use std::collections::{HashMap, HashSet};
use std::path::Path;

/// The signal heads of the network at `path`, by traffic light and link index (one head per index: SUMO
/// gives every connection of a link index the same state). Links from internal edges are pedestrian
/// crossings' signals (they leave a walking area, whose lane ends nowhere near a stop line): they are not
/// heads, and their count is logged.
pub fn parse_heads(path: &Path) -> Result<Vec<SignalHead>> {
    let mut xml = XmlStream::open(path)?;
    let mut lane_ends: HashMap<String, ([f64; 2], f64)> = HashMap::new();
    // (tl, link index, lane it leaves), in file order; lanes come before connections in net.xml, but
    // nothing here relies on it.
    let mut links: Vec<(String, usize, String, u64)> = Vec::new();
    let mut crossings = 0usize;
    while let Some(item) = xml.next()? {
        let Item::Open(el) = item else { continue };
        match el.name.as_str() {
            "lane" => {
                let shape = el.shape("shape", &xml)?;
                if let [.., a, b] = shape.as_slice() {
                    let heading = (b[1] - a[1]).atan2(b[0] - a[0]);
                    lane_ends.insert(el.req("id", &xml)?.into(), (*b, heading));
                }
            }
            "connection" => {
                let Some(tl) = el.get("tl") else { continue };
                if el.req("from", &xml)?.starts_with(':') {
                    crossings += 1;
                    continue;
                }
                let index = el.num("linkIndex", &xml)?;
                if !(index >= 0.0 && index.fract() == 0.0) {
                    return Err(xml.error(&el, format!("linkIndex {index} is not an index")));
                }
                let lane = format!("{}_{}", el.req("from", &xml)?, el.req("fromLane", &xml)?);
                links.push((tl.to_string(), index as usize, lane, el.offset));
            }
            _ => {}
        }
    }
    let mut heads: Vec<SignalHead> = Vec::new();
    let mut seen: HashSet<(String, usize)> = HashSet::new();
    for (tl, link, lane, offset) in links {
        if !seen.insert((tl.clone(), link)) {
            continue;
        }
        let Some(&([x, y], heading)) = lane_ends.get(&lane) else {
            return Err(super::xml::input_error(
                path,
                offset,
                format!(
                    "traffic light `{tl}` link {link} leaves lane `{lane}`, which the network does not have"
                ),
            ));
        };
        heads.push(SignalHead {
            tl,
            link,
            x,
            y,
            heading,
        });
    }
    if crossings > 0 {
        tracing::info!(
            "{}: {crossings} signalled pedestrian crossing link(s) left out of the signal heads",
            path.display()
        );
    }
    Ok(heads)
}

/// The states of `heads` at steps `t0 + i·dt` (`steps` of them) from the `SaveTLSStates` output at
/// `path`: at each step the last state written at or before it. A light the file names but the network
/// does not is an error, as is a state string shorter than a head's link index or holding a character
/// SUMO does not write; a light the network has and the file never names stays off.
pub fn parse_states(
    path: &Path,
    heads: &[SignalHead],
    (t0, dt, steps): (f64, f64, usize),
) -> Result<Signals> {
    let mut xml = XmlStream::open(path)?;
    let mut by_tl: HashMap<&str, Vec<usize>> = HashMap::new();
    for (i, h) in heads.iter().enumerate() {
        by_tl.entry(h.tl.as_str()).or_default().push(i);
    }
    let mut changes: Vec<Vec<(u32, u8)>> = vec![Vec::new(); heads.len()];
    let mut saw_root = false;
    while let Some(item) = xml.next()? {
        let Item::Open(el) = item else { continue };
        match el.name.as_str() {
            "tlsStates" => saw_root = true,
            "tlsState" => {
                let time = el.num("time", &xml)?;
                let id = el.req("id", &xml)?;
                let state: Vec<char> = el.req("state", &xml)?.chars().collect();
                let Some(of_tl) = by_tl.get(id) else {
                    return Err(xml.error(&el, format!("traffic light `{id}` is not in the network")));
                };
                // The first step at or after `time`: the state holds from there.
                let from = ((time - t0) / dt - 1e-6).ceil().max(0.0);
                if from >= steps as f64 {
                    continue;
                }
                let step = from as u32;
                for &h in of_tl {
                    let link = heads[h].link;
                    let Some(&c) = state.get(link) else {
                        return Err(xml.error(
                            &el,
                            format!("state `{}` has no link {link}", String::from_iter(&state)),
                        ));
                    };
                    let Some(s) = LightState::from_sumo(c) else {
                        return Err(xml.error(
                            &el,
                            format!("state character `{c}` (link {link}) is not one SUMO writes"),
                        ));
                    };
                    let list = &mut changes[h];
                    match list.last_mut() {
                        Some(last) if last.0 == step => last.1 = s as u8,
                        Some(last) if last.1 == s as u8 => {}
                        _ => list.push((step, s as u8)),
                    }
                }
            }
            _ => {}
        }
    }
    if !saw_root {
        return Err(super::xml::input_error(
            path,
            0,
            "no <tlsStates> element: not a SaveTLSStates output".into(),
        ));
    }
    Ok(Signals {
        heads: heads.to_vec(),
        changes,
    })
}
