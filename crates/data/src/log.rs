//! Logs: every actor's state at every step of one recording (a simulation run), in global coordinates.
//!
//! On disk (`logs/<id>.ulog`, little-endian):
//!
//! | bytes | content |
//! |---|---|
//! | 8 | magic `UMGLOG01` |
//! | 4 | header length H |
//! | 4 | CRC32 of the header |
//! | H | header, JSON: tracks, t0, dt, steps, chunk size, per-step record offsets, per-chunk CRC32 |
//! | 20 × records | states, step-major, sorted by track within a step: u32 track, f32 x, y, heading, speed |
//!
//! Steps are grouped in chunks of `chunk_steps`; reading a step reads and checks only its chunk, so a
//! window never loads a whole log, and a damaged byte is caught when its chunk is read.

use crate::error::{DataError, Result, corrupt, io};
use serde::{Deserialize, Serialize};
use std::fs::File;
use std::io::Write;
use std::os::unix::fs::FileExt;
use std::path::{Path, PathBuf};
use std::sync::{Arc, Mutex};
use umgen_scene::AgentCategory;

const MAGIC: &[u8; 8] = b"UMGLOG01";
const RECORD: usize = 20;
/// Steps per checksummed chunk.
pub const CHUNK_STEPS: usize = 32;
const CACHE_CHUNKS: usize = 16;

/// One actor of a log.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Track {
    /// The source's id (SUMO vehicle or person id).
    pub name: String,
    /// Category.
    pub category: AgentCategory,
    /// The source's class (SUMO vClass, e.g. `passenger`).
    pub class: String,
    /// Box length (m).
    pub length: f64,
    /// Box width (m).
    pub width: f64,
    /// Box height (m).
    pub height: f64,
}

/// One actor's state at one step: box centre and heading in global coordinates, speed along the heading.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct State {
    /// Index into the log's tracks.
    pub track: u32,
    /// Centre x (m).
    pub x: f32,
    /// Centre y (m).
    pub y: f32,
    /// Heading (rad, counter-clockwise from +x).
    pub heading: f32,
    /// Speed (m/s).
    pub speed: f32,
}

/// A whole log in memory, as importers build it.
#[derive(Debug, Clone, PartialEq)]
pub struct Log {
    /// The actors.
    pub tracks: Vec<Track>,
    /// Time of step 0 (s).
    pub t0: f64,
    /// Seconds between steps.
    pub dt: f64,
    /// States per step; within a step sorted by track, each track at most once.
    pub steps: Vec<Vec<State>>,
}

#[derive(Debug, Clone, Serialize, Deserialize)]
struct Header {
    format: String,
    version: u32,
    t0: f64,
    dt: f64,
    steps: usize,
    chunk_steps: usize,
    tracks: Vec<Track>,
    step_starts: Vec<u64>,
    chunk_crc: Vec<u32>,
}

impl Log {
    /// Writes the log to `path` (via a temporary file renamed into place).
    pub fn write(&self, path: &Path) -> Result<()> {
        let mut starts = Vec::with_capacity(self.steps.len() + 1);
        let mut body = Vec::new();
        starts.push(0u64);
        for step in &self.steps {
            for s in step {
                body.extend_from_slice(&s.track.to_le_bytes());
                for v in [s.x, s.y, s.heading, s.speed] {
                    body.extend_from_slice(&v.to_le_bytes());
                }
            }
            starts.push((body.len() / RECORD) as u64);
        }
        let chunk_crc = (0..self.steps.len().div_ceil(CHUNK_STEPS))
            .map(|c| {
                let a = starts[c * CHUNK_STEPS] as usize * RECORD;
                let b = starts[((c + 1) * CHUNK_STEPS).min(self.steps.len())] as usize * RECORD;
                crc32fast::hash(&body[a..b])
            })
            .collect();
        let header = Header {
            format: "umgen-log".into(),
            version: 1,
            t0: self.t0,
            dt: self.dt,
            steps: self.steps.len(),
            chunk_steps: CHUNK_STEPS,
            tracks: self.tracks.clone(),
            step_starts: starts,
            chunk_crc,
        };
        let json =
            serde_json::to_vec(&header).map_err(|e| corrupt(path, format!("cannot encode header: {e}")))?;
        let mut out = Vec::with_capacity(16 + json.len() + body.len());
        out.extend_from_slice(MAGIC);
        out.extend_from_slice(&(json.len() as u32).to_le_bytes());
        out.extend_from_slice(&crc32fast::hash(&json).to_le_bytes());
        out.extend_from_slice(&json);
        out.extend_from_slice(&body);
        write_atomic(path, &out)
    }
}

/// Writes `bytes` to `path` through a temporary file in the same directory, then renames it into place,
/// so that a reader never sees a half-written file.
pub fn write_atomic(path: &Path, bytes: &[u8]) -> Result<()> {
    let tmp = path.with_extension("tmp");
    let mut f = File::create(&tmp).map_err(io(&tmp))?;
    f.write_all(bytes).and_then(|()| f.sync_all()).map_err(io(&tmp))?;
    std::fs::rename(&tmp, path).map_err(io(path))
}

/// The states of one step, sharing their chunk's buffer.
#[derive(Debug, Clone)]
pub struct StepStates {
    chunk: Arc<Vec<State>>,
    range: std::ops::Range<usize>,
}

impl StepStates {
    /// States, sorted by track.
    pub fn states(&self) -> &[State] {
        &self.chunk[self.range.clone()]
    }

    /// The state of one track, if present.
    pub fn get(&self, track: u32) -> Option<&State> {
        let s = self.states();
        s.binary_search_by_key(&track, |x| x.track).ok().map(|i| &s[i])
    }
}

/// An open log file: the header in memory, states read chunk by chunk on demand.
#[derive(Debug)]
pub struct LogShard {
    path: PathBuf,
    file: File,
    header: Header,
    data_offset: u64,
    cache: Mutex<Vec<(usize, Arc<Vec<State>>)>>,
}

impl LogShard {
    /// Opens a log and checks its header and length.
    pub fn open(path: &Path) -> Result<Self> {
        let file = File::open(path).map_err(io(path))?;
        let len = file.metadata().map_err(io(path))?.len();
        let mut head = [0u8; 16];
        file.read_exact_at(&mut head, 0)
            .map_err(|_| corrupt(path, format!("{len} bytes, too short for a header")))?;
        if &head[..8] != MAGIC {
            return Err(corrupt(path, "not a umgen log (bad magic)"));
        }
        let hlen = u32::from_le_bytes([head[8], head[9], head[10], head[11]]) as u64;
        let crc = u32::from_le_bytes([head[12], head[13], head[14], head[15]]);
        if 16 + hlen > len {
            return Err(corrupt(
                path,
                format!("header of {hlen} bytes runs past the end ({len} bytes)"),
            ));
        }
        let mut json = vec![0u8; hlen as usize];
        file.read_exact_at(&mut json, 16).map_err(io(path))?;
        if crc32fast::hash(&json) != crc {
            return Err(corrupt(path, "header checksum mismatch"));
        }
        let header: Header =
            serde_json::from_slice(&json).map_err(|e| corrupt(path, format!("header: {e}")))?;
        let records = header.step_starts.last().copied().unwrap_or(0);
        let chunks = header.steps.div_ceil(header.chunk_steps.max(1));
        let consistent = header.version == 1
            && header.chunk_steps > 0
            && header.step_starts.len() == header.steps + 1
            && header.step_starts.windows(2).all(|w| w[0] <= w[1])
            && header.chunk_crc.len() == chunks
            && header.dt > 0.0;
        if !consistent {
            return Err(corrupt(path, "inconsistent header"));
        }
        let data_offset = 16 + hlen;
        let expected = data_offset + records * RECORD as u64;
        if len != expected {
            return Err(corrupt(
                path,
                format!("{len} bytes, the header describes {expected}"),
            ));
        }
        Ok(Self {
            path: path.into(),
            file,
            header,
            data_offset,
            cache: Mutex::new(Vec::new()),
        })
    }

    /// The file.
    pub fn path(&self) -> &Path {
        &self.path
    }

    /// The actors.
    pub fn tracks(&self) -> &[Track] {
        &self.header.tracks
    }

    /// Number of steps.
    pub fn steps(&self) -> usize {
        self.header.steps
    }

    /// Seconds between steps.
    pub fn dt(&self) -> f64 {
        self.header.dt
    }

    /// Time of step 0.
    pub fn t0(&self) -> f64 {
        self.header.t0
    }

    /// The states of step `s`.
    pub fn step(&self, s: usize) -> Result<StepStates> {
        if s >= self.header.steps {
            return Err(DataError::Request {
                path: self.path.clone(),
                message: format!("step {s} of a log with {} steps", self.header.steps),
            });
        }
        let c = s / self.header.chunk_steps;
        let chunk = self.chunk(c)?;
        let base = self.header.step_starts[c * self.header.chunk_steps] as usize;
        let range =
            self.header.step_starts[s] as usize - base..self.header.step_starts[s + 1] as usize - base;
        Ok(StepStates { chunk, range })
    }

    fn chunk(&self, c: usize) -> Result<Arc<Vec<State>>> {
        let mut cache = self
            .cache
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner);
        if let Some(i) = cache.iter().position(|(k, _)| *k == c) {
            let hit = cache.remove(i);
            let states = hit.1.clone();
            cache.push(hit);
            return Ok(states);
        }
        let h = &self.header;
        let (a, b) = (
            h.step_starts[c * h.chunk_steps],
            h.step_starts[((c + 1) * h.chunk_steps).min(h.steps)],
        );
        let mut bytes = vec![0u8; (b - a) as usize * RECORD];
        self.file
            .read_exact_at(&mut bytes, self.data_offset + a * RECORD as u64)
            .map_err(io(&self.path))?;
        if crc32fast::hash(&bytes) != h.chunk_crc[c] {
            return Err(corrupt(
                &self.path,
                format!(
                    "checksum mismatch in steps {}..{}",
                    c * h.chunk_steps,
                    ((c + 1) * h.chunk_steps).min(h.steps)
                ),
            ));
        }
        let f = |r: &[u8], i: usize| f32::from_le_bytes([r[i], r[i + 1], r[i + 2], r[i + 3]]);
        let states: Vec<State> = bytes
            .chunks_exact(RECORD)
            .map(|r| State {
                track: u32::from_le_bytes([r[0], r[1], r[2], r[3]]),
                x: f(r, 4),
                y: f(r, 8),
                heading: f(r, 12),
                speed: f(r, 16),
            })
            .collect();
        if states.iter().any(|s| s.track as usize >= h.tracks.len()) {
            return Err(corrupt(
                &self.path,
                format!("a state in chunk {c} names a track that does not exist"),
            ));
        }
        let states = Arc::new(states);
        if cache.len() >= CACHE_CHUNKS {
            cache.remove(0);
        }
        cache.push((c, states.clone()));
        Ok(states)
    }

    /// Reads the whole log into memory.
    pub fn read_all(&self) -> Result<Log> {
        let steps = (0..self.steps())
            .map(|s| Ok(self.step(s)?.states().to_vec()))
            .collect::<Result<_>>()?;
        Ok(Log {
            tracks: self.header.tracks.clone(),
            t0: self.header.t0,
            dt: self.header.dt,
            steps,
        })
    }
}
