//! Reading a dataset: clips and windows of frames, with their road networks.

use crate::error::{DataError, Result, corrupt, io};
use crate::index::{ClipEntry, Index};
use crate::log::LogShard;
use crate::signals::Signals;
use crate::view::{ViewOptions, frames};
use std::collections::HashMap;
use std::path::{Path, PathBuf};
use std::sync::{Arc, Mutex};
use umgen_scene::{RoadNetwork, SceneClip};

/// A window of frames within a clip: frames `start, start + gap, …` (`frames` of them).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub struct Window {
    /// Clip index.
    pub clip: usize,
    /// First frame within the clip.
    pub start: usize,
}

/// An open dataset directory. Logs are opened and road networks loaded on first use and shared.
#[derive(Debug)]
pub struct Dataset {
    root: PathBuf,
    index: Index,
    options: ViewOptions,
    logs: Mutex<HashMap<String, Arc<LogShard>>>,
    networks: Mutex<HashMap<String, Arc<RoadNetwork>>>,
    signals: Mutex<HashMap<String, Arc<Signals>>>,
}

impl Dataset {
    /// Opens `root` and reads its index.
    pub fn open(root: &Path) -> Result<Self> {
        let index = Index::load(root)?;
        Ok(Self {
            root: root.into(),
            index,
            options: ViewOptions::default(),
            logs: Mutex::new(HashMap::new()),
            networks: Mutex::new(HashMap::new()),
            signals: Mutex::new(HashMap::new()),
        })
    }

    /// Uses other view options.
    pub fn with_options(mut self, options: ViewOptions) -> Self {
        self.options = options;
        self
    }

    /// The directory.
    pub fn root(&self) -> &Path {
        &self.root
    }

    /// The index.
    pub fn index(&self) -> &Index {
        &self.index
    }

    /// All clips.
    pub fn clips(&self) -> &[ClipEntry] {
        &self.index.clips
    }

    /// The index of the clip with id `id`.
    pub fn find_clip(&self, id: &str) -> Result<usize> {
        self.index
            .clips
            .iter()
            .position(|c| c.id == id)
            .ok_or_else(|| self.request(format!("no clip `{id}`")))
    }

    fn request(&self, message: String) -> DataError {
        DataError::Request {
            path: self.root.clone(),
            message,
        }
    }

    /// The open log `id`.
    pub fn log(&self, id: &str) -> Result<Arc<LogShard>> {
        let mut logs = self
            .logs
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner);
        if let Some(l) = logs.get(id) {
            return Ok(l.clone());
        }
        let entry = self
            .index
            .logs
            .iter()
            .find(|l| l.id == id)
            .ok_or_else(|| self.request(format!("no log `{id}`")))?;
        let shard = Arc::new(LogShard::open(&self.root.join(&entry.file))?);
        if shard.steps() != entry.steps || shard.tracks().len() != entry.tracks {
            return Err(corrupt(
                shard.path(),
                format!(
                    "holds {} steps and {} tracks, the index says {} and {}",
                    shard.steps(),
                    shard.tracks().len(),
                    entry.steps,
                    entry.tracks
                ),
            ));
        }
        logs.insert(id.into(), shard.clone());
        Ok(shard)
    }

    /// The road network `id`, checked against its CRC32 in the index.
    pub fn network(&self, id: &str) -> Result<Arc<RoadNetwork>> {
        let mut nets = self
            .networks
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner);
        if let Some(n) = nets.get(id) {
            return Ok(n.clone());
        }
        let entry = self
            .index
            .networks
            .iter()
            .find(|n| n.id == id)
            .ok_or_else(|| self.request(format!("no network `{id}`")))?;
        let net = Arc::new(load_network(&self.root.join(&entry.file), entry.crc32)?);
        nets.insert(id.into(), net.clone());
        Ok(net)
    }

    /// The traffic signals of log `id`, when it has them (loaded on first use and shared).
    pub fn signals(&self, id: &str) -> Result<Option<Arc<Signals>>> {
        let Some(entry) = self
            .index
            .logs
            .iter()
            .find(|l| l.id == id)
            .and_then(|l| l.signals.as_ref())
        else {
            return Ok(None);
        };
        let mut all = self
            .signals
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner);
        if let Some(s) = all.get(id) {
            return Ok(Some(s.clone()));
        }
        let s = Arc::new(Signals::load(&self.root.join(&entry.file), entry.crc32)?);
        all.insert(id.into(), s.clone());
        Ok(Some(s))
    }

    /// The id of the road network of clip `clip`'s log, if the index names one.
    pub fn clip_network_id(&self, clip: usize) -> Option<&str> {
        let entry = self.index.clips.get(clip)?;
        self.index
            .logs
            .iter()
            .find(|l| l.id == entry.log)
            .map(|l| l.network.as_str())
    }

    /// A whole clip at its native interval.
    pub fn read_clip(&self, clip: usize) -> Result<SceneClip> {
        let frames = self.clip(clip)?.frames;
        self.read_window(clip, 0, frames, 1)
    }

    fn clip(&self, clip: usize) -> Result<&ClipEntry> {
        self.index
            .clips
            .get(clip)
            .ok_or_else(|| self.request(format!("clip index {clip} out of {}", self.index.clips.len())))
    }

    /// Frames `start, start + gap, …` of a clip (`frames` of them), at `gap × frame_interval` seconds
    /// apart, with the clip's road network attached.
    pub fn read_window(&self, clip: usize, start: usize, frames_n: usize, gap: usize) -> Result<SceneClip> {
        let entry = self.clip(clip)?;
        if gap == 0 || frames_n == 0 || start + (frames_n - 1) * gap >= entry.frames {
            return Err(self.request(format!(
                "clip `{}` has {} frames; a window of {frames_n} frames from {start} with gap {gap} does not fit",
                entry.id, entry.frames
            )));
        }
        let log = self.log(&entry.log)?;
        let first = entry.first_step + start;
        let steps: Vec<_> = (0..frames_n)
            .map(|i| log.step(first + i * gap))
            .collect::<Result<_>>()?;
        let before = match first.checked_sub(gap) {
            Some(s) => log.step(s)?.get(entry.ego_track).copied(),
            None => None,
        };
        let slices: Vec<_> = steps.iter().map(|s| s.states()).collect();
        let dt = self.index.frame_interval * gap as f64;
        let mut frames = frames(
            log.path(),
            log.tracks(),
            entry.ego_track,
            &slices,
            before.as_ref(),
            dt,
            &self.options,
        )?;
        if let Some(signals) = self.signals(&entry.log)? {
            let steps: Vec<usize> = (0..frames_n).map(|i| first + i * gap).collect();
            signals.attach(&mut frames, &steps, self.options.agent_range);
        }
        let network = self.network(self.clip_network_id(clip).unwrap_or_default())?;
        let id = if start == 0 && gap == 1 && frames_n == entry.frames {
            entry.id.clone()
        } else {
            format!("{}@{start}x{gap}", entry.id)
        };
        let clip = SceneClip::new(id, dt, frames).map_err(|e| corrupt(log.path(), e.to_string()))?;
        Ok(clip.with_network(network))
    }

    /// Every window of `frames` frames at `gap` in the clips of `split` (all splits when `None`), in
    /// index order.
    pub fn windows(&self, frames: usize, gap: usize, split: Option<&str>) -> Vec<Window> {
        let span = frames.saturating_sub(1) * gap.max(1);
        let mut out = Vec::new();
        for (i, c) in self.index.clips.iter().enumerate() {
            if split.is_some_and(|s| s != c.split) || frames == 0 || c.frames <= span {
                continue;
            }
            out.extend((0..c.frames - span).map(|start| Window { clip: i, start }));
        }
        out
    }
}

/// Loads a road network file, checking its CRC32.
pub fn load_network(path: &Path, crc32: u32) -> Result<RoadNetwork> {
    let bytes = std::fs::read(path).map_err(io(path))?;
    if crc32fast::hash(&bytes) != crc32 {
        return Err(corrupt(path, "checksum mismatch (the index holds another CRC32)"));
    }
    serde_json::from_slice(&bytes).map_err(|e| corrupt(path, e.to_string()))
}
