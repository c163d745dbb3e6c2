//! The dataset index (`index.json`): networks, logs, clips and statistics.

use crate::error::{DataError, Result, corrupt, io};
use crate::log::write_atomic;
use crate::stats::Stats;
use serde::{Deserialize, Serialize};
use std::path::Path;

/// File name of the index inside a dataset directory.
pub const INDEX_FILE: &str = "index.json";

/// What a dataset holds.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Index {
    /// Always `umgen-dataset`.
    pub format: String,
    /// Format version (1).
    pub version: u32,
    /// Seconds between log steps; every log of a dataset shares it.
    pub frame_interval: f64,
    /// Road networks, each shared by the logs recorded on it.
    pub networks: Vec<NetworkEntry>,
    /// Logs (recordings), each on one network.
    pub logs: Vec<LogEntry>,
    /// Clips: one ego track over a range of steps of one log.
    pub clips: Vec<ClipEntry>,
    /// Statistics over every frame of every clip.
    pub stats: Stats,
}

/// A road network file.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct NetworkEntry {
    /// Id.
    pub id: String,
    /// Path relative to the dataset directory.
    pub file: String,
    /// CRC32 of the file.
    pub crc32: u32,
    /// Drawable elements.
    pub elements: usize,
}

/// A log file.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct LogEntry {
    /// Id.
    pub id: String,
    /// Network id.
    pub network: String,
    /// Path relative to the dataset directory.
    pub file: String,
    /// Where it came from (e.g. `sumo: grid.net.xml + fcd.xml`).
    pub source: String,
    /// Steps.
    pub steps: usize,
    /// Actors.
    pub tracks: usize,
    /// Split its clips belong to (`train`, `val`, `test`).
    pub split: String,
    /// Statistics over the frames of its clips.
    pub stats: Stats,
    /// Its traffic signals, when they were imported (`umgen data sumo --tls`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub signals: Option<SignalsEntry>,
}

/// A log's traffic signals file ([`crate::Signals`]).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SignalsEntry {
    /// Path relative to the dataset directory.
    pub file: String,
    /// CRC32 of the file.
    pub crc32: u32,
    /// Signal heads.
    pub heads: usize,
}

/// A clip: `frames` consecutive steps of one log seen from one ego track.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ClipEntry {
    /// Id, unique in the dataset (`<log>/<ego name>:<k>`).
    pub id: String,
    /// Log id.
    pub log: String,
    /// The ego's track index in the log.
    pub ego_track: u32,
    /// First step.
    pub first_step: usize,
    /// Number of steps.
    pub frames: usize,
    /// Split (copied from the log).
    pub split: String,
}

impl Index {
    /// An empty index for logs stepping every `frame_interval` seconds.
    pub fn new(frame_interval: f64) -> Self {
        Self {
            format: "umgen-dataset".into(),
            version: 1,
            frame_interval,
            networks: Vec::new(),
            logs: Vec::new(),
            clips: Vec::new(),
            stats: Stats::default(),
        }
    }

    /// Reads `dir/index.json`.
    pub fn load(dir: &Path) -> Result<Self> {
        let path = dir.join(INDEX_FILE);
        let text = std::fs::read(&path).map_err(io(&path))?;
        let index: Index = serde_json::from_slice(&text).map_err(|e| corrupt(&path, e.to_string()))?;
        if index.format != "umgen-dataset" || index.version != 1 {
            return Err(corrupt(
                &path,
                format!(
                    "format {} v{} is not umgen-dataset v1",
                    index.format, index.version
                ),
            ));
        }
        index.check(&path)?;
        Ok(index)
    }

    /// Writes `dir/index.json` atomically.
    pub fn save(&self, dir: &Path) -> Result<()> {
        let path = dir.join(INDEX_FILE);
        let text = serde_json::to_vec_pretty(self).map_err(|e| corrupt(&path, e.to_string()))?;
        write_atomic(&path, &text)
    }

    /// Checks cross-references: clips name existing logs, logs existing networks, ids are unique.
    pub fn check(&self, path: &Path) -> Result<()> {
        let bad = |m: String| {
            Err(DataError::Corrupt {
                path: path.into(),
                reason: m,
            })
        };
        let mut networks = std::collections::HashSet::new();
        for n in &self.networks {
            if !networks.insert(n.id.as_str()) {
                return bad(format!("network id `{}` appears twice", n.id));
            }
        }
        let mut logs = std::collections::HashSet::new();
        for l in &self.logs {
            if !logs.insert(l.id.as_str()) {
                return bad(format!("log id `{}` appears twice", l.id));
            }
            if !self.networks.iter().any(|n| n.id == l.network) {
                return bad(format!("log `{}` names unknown network `{}`", l.id, l.network));
            }
        }
        let mut clips = std::collections::HashSet::new();
        for c in &self.clips {
            if !clips.insert(c.id.as_str()) {
                return bad(format!("clip id `{}` appears twice", c.id));
            }
            match self.logs.iter().find(|l| l.id == c.log) {
                None => return bad(format!("clip `{}` names unknown log `{}`", c.id, c.log)),
                Some(l) if c.first_step + c.frames > l.steps || c.frames == 0 => {
                    return bad(format!(
                        "clip `{}` spans steps {}..{} of a {}-step log",
                        c.id,
                        c.first_step,
                        c.first_step + c.frames,
                        l.steps
                    ));
                }
                Some(_) => {}
            }
        }
        Ok(())
    }
}
