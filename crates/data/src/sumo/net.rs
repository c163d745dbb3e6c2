//! SUMO `.net.xml` → [`RoadNetwork`]: lanes, connectors, crossings, junctions, stop lines, dividers.

use super::geometry::{direction, offset, round_network, strip};
use super::xml::{Element, Item, XmlStream};
use crate::error::Result;
use std::collections::{HashMap, HashSet};
use std::path::Path;
use umgen_scene::{Crosswalk, Marking, RoadNetwork};

/// SUMO's lane width when a lane gives none (m).
const DEFAULT_LANE_WIDTH: f64 = 3.2;
/// Width of painted stop lines (m).
const STOP_LINE_WIDTH: f64 = 0.5;
/// Width of painted lane dividers (m).
const DIVIDER_WIDTH: f64 = 0.15;
/// Junction types whose incoming lanes end at a stop line.
const STOP_JUNCTIONS: [&str; 8] = [
    "traffic_light",
    "traffic_light_unregulated",
    "traffic_light_right_on_red",
    "allway_stop",
    "priority_stop",
    "right_before_left",
    "left_before_right",
    "zipper",
];
const RAIL: [&str; 9] = [
    "rail",
    "rail_urban",
    "rail_electric",
    "rail_fast",
    "tram",
    "cable_car",
    "subway",
    "ship",
    "aircraft",
];

/// A parsed network and what FCD traces are checked against.
#[derive(Debug)]
pub struct SumoNet {
    /// The drawable geometry.
    pub network: RoadNetwork,
    /// Every lane id (normal and internal).
    pub lanes: HashSet<String>,
    /// Every edge id.
    pub edges: HashSet<String>,
    /// `convBoundary` of the network (min x, min y, max x, max y).
    pub boundary: [f64; 4],
}

#[derive(Debug)]
struct Lane {
    id: String,
    width: f64,
    shape: Vec<[f64; 2]>,
    kind: LaneKind,
}

#[derive(Debug, Clone, Copy, PartialEq)]
enum LaneKind {
    Drivable,
    Sidewalk,
    Other,
}

fn lane_kind(el: &Element) -> LaneKind {
    let classes = |k: &str| {
        el.get(k)
            .map(|v| v.split_whitespace().map(str::to_string).collect::<Vec<_>>())
    };
    match classes("allow") {
        Some(a) if a.iter().all(|c| c == "pedestrian") => LaneKind::Sidewalk,
        Some(a) if a.iter().all(|c| RAIL.contains(&c.as_str())) => LaneKind::Other,
        _ => LaneKind::Drivable,
    }
}

#[derive(Debug, Default)]
struct Edge {
    id: String,
    function: String,
    from: String,
    to: String,
    lanes: Vec<Lane>,
}

/// Parses a SUMO network file; `id` names the network.
pub fn parse_net(path: &Path, id: &str) -> Result<SumoNet> {
    let mut xml = XmlStream::open(path)?;
    let mut net = RoadNetwork {
        id: id.into(),
        ..RoadNetwork::default()
    };
    let (mut edges, mut junction_types): (Vec<Edge>, HashMap<String, String>) = (Vec::new(), HashMap::new());
    let mut current: Option<Edge> = None;
    let mut boundary = None;
    let mut saw_net = false;
    while let Some(item) = xml.next()? {
        match item {
            Item::Open(el) => match el.name.as_str() {
                "net" => saw_net = true,
                "location" => {
                    let b = el.req("convBoundary", &xml)?;
                    let v: Vec<f64> = b.split(',').filter_map(|x| x.parse().ok()).collect();
                    boundary =
                        Some(<[f64; 4]>::try_from(v).map_err(|_| {
                            xml.error(&el, format!("convBoundary `{b}` is not four numbers"))
                        })?);
                }
                "edge" => {
                    current = Some(Edge {
                        id: el.req("id", &xml)?.into(),
                        function: el.get("function").unwrap_or("normal").into(),
                        from: el.get("from").unwrap_or_default().into(),
                        to: el.get("to").unwrap_or_default().into(),
                        lanes: Vec::new(),
                    });
                }
                "lane" => {
                    let Some(edge) = current.as_mut() else {
                        return Err(xml.error(&el, "<lane> outside an <edge>"));
                    };
                    let shape = el.shape("shape", &xml)?;
                    if shape.len() < 2 {
                        return Err(xml.error(&el, "lane shape needs at least two points"));
                    }
                    let width = el.opt_num("width", &xml)?.unwrap_or(DEFAULT_LANE_WIDTH);
                    edge.lanes.push(Lane {
                        id: el.req("id", &xml)?.into(),
                        width,
                        shape,
                        kind: lane_kind(&el),
                    });
                }
                "junction" => {
                    let jtype = el.get("type").unwrap_or("unknown").to_string();
                    junction_types.insert(el.req("id", &xml)?.into(), jtype.clone());
                    if jtype != "internal" && jtype != "dead_end" && el.get("shape").is_some() {
                        let shape = el.shape("shape", &xml)?;
                        if shape.len() >= 3 {
                            net.intersections.push(shape);
                        }
                    }
                }
                _ => {}
            },
            Item::Close(name) if name == "edge" => edges.extend(current.take()),
            Item::Close(_) => {}
        }
    }
    if !saw_net {
        return Err(super::xml::input_error(
            path,
            0,
            "not a SUMO network: no <net> element".into(),
        ));
    }
    let boundary =
        boundary.ok_or_else(|| super::xml::input_error(path, 0, "no <location convBoundary=…>".into()))?;
    let pairs: HashSet<(String, String)> = edges.iter().map(|e| (e.from.clone(), e.to.clone())).collect();
    let (mut lanes, mut edge_ids) = (HashSet::new(), HashSet::new());
    for e in &edges {
        edge_ids.insert(e.id.clone());
        lanes.extend(e.lanes.iter().map(|l| l.id.clone()));
        let stop = junction_types
            .get(&e.to)
            .is_some_and(|t| STOP_JUNCTIONS.contains(&t.as_str()));
        let opposite = e.from < e.to && pairs.contains(&(e.to.clone(), e.from.clone()));
        add_edge(&mut net, e, stop, opposite);
    }
    round_network(&mut net);
    Ok(SumoNet {
        network: net,
        lanes,
        edges: edge_ids,
        boundary,
    })
}

fn add_edge(net: &mut RoadNetwork, e: &Edge, stop: bool, opposite: bool) {
    match e.function.as_str() {
        "normal" => {
            // Lanes come in index order, rightmost first.
            let drivable: Vec<&Lane> = e.lanes.iter().filter(|l| l.kind == LaneKind::Drivable).collect();
            for l in &e.lanes {
                match l.kind {
                    LaneKind::Drivable => net.lanes.push(strip(&l.shape, l.width)),
                    LaneKind::Sidewalk => net.sidewalks.push(strip(&l.shape, l.width)),
                    LaneKind::Other => {}
                }
            }
            // SUMO numbers lanes from the right; the left boundary of lane i is the divider to lane i + 1.
            let n = drivable.len();
            for (i, l) in drivable.iter().enumerate() {
                if i + 1 < n || opposite {
                    net.dividers.push(Marking {
                        line: offset(&l.shape, l.width / 2.0),
                        width: DIVIDER_WIDTH,
                    });
                }
                if stop {
                    net.stop_lines.push(stop_line(&l.shape, l.width));
                }
            }
        }
        "internal" => net.connectors.extend(
            e.lanes
                .iter()
                .filter(|l| l.kind == LaneKind::Drivable)
                .map(|l| strip(&l.shape, l.width)),
        ),
        "crossing" => net.crosswalks.extend(e.lanes.iter().map(|l| Crosswalk {
            polygon: strip(&l.shape, l.width),
            direction: direction(&l.shape),
        })),
        "walkingarea" => net.sidewalks.extend(
            e.lanes
                .iter()
                .filter(|l| l.shape.len() >= 3)
                .map(|l| l.shape.clone()),
        ),
        _ => {}
    }
}

/// A stop line across the end of a lane, set back by half its width so that it lies on the lane.
fn stop_line(shape: &[[f64; 2]], width: f64) -> Marking {
    let n = shape.len();
    let d = direction(&shape[n - 2..]);
    let back = STOP_LINE_WIDTH / 2.0;
    let c = [shape[n - 1][0] - d[0] * back, shape[n - 1][1] - d[1] * back];
    let h = width / 2.0;
    Marking {
        line: vec![
            [c[0] - d[1] * h, c[1] + d[0] * h],
            [c[0] + d[1] * h, c[1] - d[0] * h],
        ],
        width: STOP_LINE_WIDTH,
    }
}
