//! `umgen data sumo`: a SUMO network and FCD trace → a log, a network and clips in a dataset.

use super::fcd::parse_fcd;
use super::net::parse_net;
use super::tls::{parse_heads, parse_states};
use super::types::TypeTable;
use crate::error::{DataError, Result, corrupt, io};
use crate::index::{ClipEntry, INDEX_FILE, Index, LogEntry, NetworkEntry, SignalsEntry};
use crate::log::{Log, write_atomic};
use crate::stats::clip_stats;
use crate::view::ViewOptions;
use std::path::{Path, PathBuf};
use umgen_scene::AgentCategory;

/// Vehicle classes that can be the ego by default: cars and vans.
pub const EGO_CLASSES: [&str; 7] = [
    "passenger",
    "private",
    "taxi",
    "evehicle",
    "delivery",
    "emergency",
    "hov",
];

/// What to import and how to cut it into clips.
#[derive(Debug, Clone)]
pub struct ImportOptions {
    /// The `.net.xml`.
    pub net: PathBuf,
    /// The FCD trace.
    pub fcd: PathBuf,
    /// Route or additional files with the `<vType>`s the trace uses.
    pub types: Vec<PathBuf>,
    /// Dataset directory (created, or extended when it exists).
    pub out: PathBuf,
    /// Log id (default: the FCD file name up to its first dot).
    pub name: Option<String>,
    /// Network id (default: the network file name up to its first dot).
    pub network_name: Option<String>,
    /// Split of the new clips.
    pub split: String,
    /// Frames per clip; longer trajectories become several clips.
    pub clip_frames: usize,
    /// Shortest clip kept (a trajectory's last piece shorter than this is dropped).
    pub min_frames: usize,
    /// Vehicle classes that can be the ego.
    pub ego_classes: Vec<String>,
    /// Use every n-th qualifying vehicle as an ego (1 = all).
    pub ego_every: usize,
    /// How frames are cut.
    pub view: ViewOptions,
    /// SUMO's traffic-light states for the trace (`SaveTLSStates` output): stored beside the log, and
    /// every frame then lists the signal heads in its view ([`crate::Signals`]).
    pub tls: Option<PathBuf>,
}

impl ImportOptions {
    /// Options with the defaults: split `train`, 40-frame clips of at least 21 frames, every car an ego.
    pub fn new(net: PathBuf, fcd: PathBuf, out: PathBuf) -> Self {
        Self {
            net,
            fcd,
            types: Vec::new(),
            out,
            name: None,
            network_name: None,
            split: "train".into(),
            clip_frames: 40,
            min_frames: 21,
            ego_classes: EGO_CLASSES.iter().map(|s| s.to_string()).collect(),
            ego_every: 1,
            view: ViewOptions::default(),
            tls: None,
        }
    }
}

/// What an import did.
#[derive(Debug, Clone, PartialEq)]
pub struct ImportReport {
    /// Log id.
    pub log: String,
    /// Network id.
    pub network: String,
    /// Steps of the log.
    pub steps: usize,
    /// Actors of the log.
    pub tracks: usize,
    /// Clips added.
    pub clips: usize,
    /// Frames in the added clips.
    pub frames: u64,
    /// Trace records of unmodelled classes left out.
    pub skipped: u64,
    /// Signal heads imported with their states (0 without `tls`).
    pub signal_heads: usize,
}

fn file_name(p: &Path) -> String {
    p.file_name()
        .map_or_else(|| p.display().to_string(), |n| n.to_string_lossy().into_owned())
}

fn stem(p: &Path) -> String {
    p.file_name()
        .and_then(|n| n.to_str())
        .and_then(|n| n.split('.').next())
        .unwrap_or("data")
        .to_string()
}

/// Imports one network and trace into `options.out`. Everything is parsed and checked before anything is
/// written; files are written to temporary names and renamed, and the index last, so a failure leaves the
/// dataset as it was.
pub fn import(options: &ImportOptions) -> Result<ImportReport> {
    let log_id = options.name.clone().unwrap_or_else(|| stem(&options.fcd));
    let net_id = options.network_name.clone().unwrap_or_else(|| stem(&options.net));
    let net = parse_net(&options.net, &net_id)?;
    let types = TypeTable::load(&options.types)?;
    let fcd = parse_fcd(&options.fcd, &net, &types)?;
    let signals = match &options.tls {
        Some(tls) => {
            let heads = parse_heads(&options.net)?;
            let log = &fcd.log;
            Some(parse_states(tls, &heads, (log.t0, log.dt, log.steps.len()))?)
        }
        None => None,
    };
    let out = &options.out;
    let mut index = if out.join(INDEX_FILE).exists() {
        Index::load(out)?
    } else {
        Index::new(fcd.log.dt)
    };
    let request = |message: String| DataError::Request {
        path: out.clone(),
        message,
    };
    if (index.frame_interval - fcd.log.dt).abs() > 1e-9 {
        return Err(request(format!(
            "{} steps every {} s, the dataset every {} s",
            options.fcd.display(),
            fcd.log.dt,
            index.frame_interval
        )));
    }
    if index.logs.iter().any(|l| l.id == log_id) {
        return Err(request(format!(
            "the dataset already has a log `{log_id}` (choose another --name)"
        )));
    }
    let net_json = serde_json::to_vec(&net.network).map_err(|e| corrupt(&options.net, e.to_string()))?;
    let net_crc = crc32fast::hash(&net_json);
    let existing_net = index.networks.iter().find(|n| n.id == net_id);
    if existing_net.is_some_and(|n| n.crc32 != net_crc) {
        return Err(request(format!(
            "the dataset has another network called `{net_id}` (choose another --network-name)"
        )));
    }
    let log_file = format!("logs/{log_id}.ulog");
    let clips = cut_clips(&fcd.log, options, &log_id);
    if clips.is_empty() {
        return Err(request(format!(
            "{}: no ego vehicle stays {} steps; nothing to import",
            options.fcd.display(),
            options.min_frames
        )));
    }
    let stats = clip_stats(&fcd.log, &clips, &options.view, &out.join(&log_file))?;
    for dir in ["logs", "networks"] {
        std::fs::create_dir_all(out.join(dir)).map_err(io(out.join(dir)))?;
    }
    if existing_net.is_none() {
        let file = format!("networks/{net_id}.json");
        write_atomic(&out.join(&file), &net_json)?;
        index.networks.push(NetworkEntry {
            id: net_id.clone(),
            file,
            crc32: net_crc,
            elements: net.network.element_count(),
        });
    }
    let signals = match &signals {
        Some(s) => {
            let file = format!("logs/{log_id}.signals.json");
            let crc32 = s.save(&out.join(&file))?;
            Some(SignalsEntry {
                file,
                crc32,
                heads: s.heads.len(),
            })
        }
        None => None,
    };
    fcd.log.write(&out.join(&log_file))?;
    let report = ImportReport {
        log: log_id.clone(),
        network: net_id.clone(),
        steps: fcd.log.steps.len(),
        tracks: fcd.log.tracks.len(),
        clips: clips.len(),
        frames: stats.frames,
        skipped: fcd.skipped,
        signal_heads: signals.as_ref().map_or(0, |s| s.heads),
    };
    index.stats.merge(&stats);
    index.logs.push(LogEntry {
        id: log_id,
        network: net_id,
        file: log_file,
        // File names only: directories differ between machines and runs.
        source: format!("sumo: {} + {}", file_name(&options.net), file_name(&options.fcd)),
        steps: report.steps,
        tracks: report.tracks,
        split: options.split.clone(),
        stats,
        signals,
    });
    index.clips.extend(clips);
    index.check(&out.join(INDEX_FILE))?;
    index.save(out)?;
    Ok(report)
}

/// Clips of every qualifying ego: each uninterrupted presence cut into `clip_frames` pieces.
fn cut_clips(log: &Log, o: &ImportOptions, log_id: &str) -> Vec<ClipEntry> {
    let mut runs: Vec<Vec<(usize, usize)>> = vec![Vec::new(); log.tracks.len()];
    for (s, step) in log.steps.iter().enumerate() {
        for st in step {
            let r = &mut runs[st.track as usize];
            match r.last_mut() {
                Some((start, len)) if *start + *len == s => *len += 1,
                _ => r.push((s, 1)),
            }
        }
    }
    let egos = log
        .tracks
        .iter()
        .enumerate()
        .filter(|(_, t)| t.category == AgentCategory::Vehicle && o.ego_classes.contains(&t.class))
        .step_by(o.ego_every.max(1));
    let mut clips = Vec::new();
    for (i, t) in egos {
        let mut k = 0;
        for &(start, len) in &runs[i] {
            let mut at = 0;
            while len - at >= o.min_frames.max(1) {
                let frames = (len - at).min(o.clip_frames.max(o.min_frames));
                clips.push(ClipEntry {
                    id: format!("{log_id}/{}:{k}", t.name),
                    log: log_id.into(),
                    ego_track: i as u32,
                    first_step: start + at,
                    frames,
                    split: o.split.clone(),
                });
                at += frames;
                k += 1;
            }
        }
    }
    clips
}
