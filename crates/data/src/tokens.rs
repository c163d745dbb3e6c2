//! Token caches: every frame of a dataset as one row of N token ids, so that training never renders or
//! runs tokenizers.
//!
//! ```text
//! TOKDIR/tokens.json          layout fingerprint, N, frame interval, shards and their clips, SHA-256
//! TOKDIR/shards/<log>.tok     64-byte header, then rows × N little-endian u16 ids
//! ```
//!
//! The header is `UMGTOK01`, `u32` N, `u32` 0, `u64` rows, zero-padded to 64 bytes, so a shard can be
//! memory-mapped as a `[rows, N]` u16 array at offset 64 (`numpy.memmap(f, "<u2", "r", 64, (rows, N))`).
//! Shards are written under a temporary name and renamed, and the index is rewritten after each shard, so
//! an interrupted `umgen tokenize` keeps what it finished and a re-run skips it.

use crate::dataset::Window;
use crate::error::{DataError, Result, corrupt, io};
use crate::log::write_atomic;
use serde::{Deserialize, Serialize};
use sha2::{Digest, Sha256};
use std::fs::File;
use std::os::unix::fs::FileExt;
use std::path::{Path, PathBuf};

/// Index file of a token cache.
pub const TOKENS_INDEX: &str = "tokens.json";
const MAGIC: &[u8; 8] = b"UMGTOK01";
const HEADER: u64 = 64;

/// A token cache's index.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct TokenIndex {
    /// Always `umgen-tokens`.
    pub format: String,
    /// Format version (1).
    pub version: u32,
    /// Frame layout fingerprint of the modalities that made the tokens.
    pub fingerprint: String,
    /// Tokens per frame (N).
    pub tokens_per_frame: usize,
    /// Seconds between frames of a clip.
    pub frame_interval: f64,
    /// Shards, one per log.
    pub shards: Vec<TokenShard>,
}

/// One shard: the clips of one log.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct TokenShard {
    /// Log id.
    pub log: String,
    /// Path relative to the cache directory.
    pub file: String,
    /// Rows in the file.
    pub rows: usize,
    /// SHA-256 of the file.
    pub sha256: String,
    /// Its clips.
    pub clips: Vec<TokenClip>,
}

/// Where a clip's frames are in its shard.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct TokenClip {
    /// Clip id.
    pub id: String,
    /// Split.
    pub split: String,
    /// First row.
    pub start: usize,
    /// Frames.
    pub frames: usize,
}

fn sha256(b: &[u8]) -> String {
    Sha256::digest(b).iter().map(|x| format!("{x:02x}")).collect()
}

impl TokenIndex {
    /// An empty index.
    pub fn new(fingerprint: &str, tokens_per_frame: usize, frame_interval: f64) -> Self {
        Self {
            format: "umgen-tokens".into(),
            version: 1,
            fingerprint: fingerprint.into(),
            tokens_per_frame,
            frame_interval,
            shards: Vec::new(),
        }
    }

    /// Reads `dir/tokens.json`, if present.
    pub fn load(dir: &Path) -> Result<Option<Self>> {
        let path = dir.join(TOKENS_INDEX);
        if !path.exists() {
            return Ok(None);
        }
        let text = std::fs::read(&path).map_err(io(&path))?;
        let idx: Self = serde_json::from_slice(&text).map_err(|e| corrupt(&path, e.to_string()))?;
        if idx.format != "umgen-tokens" || idx.version != 1 {
            return Err(corrupt(
                &path,
                format!("format {} v{} is not umgen-tokens v1", idx.format, idx.version),
            ));
        }
        Ok(Some(idx))
    }

    /// Writes `dir/tokens.json` atomically.
    pub fn save(&self, dir: &Path) -> Result<()> {
        let path = dir.join(TOKENS_INDEX);
        write_atomic(
            &path,
            &serde_json::to_vec_pretty(self).map_err(|e| corrupt(&path, e.to_string()))?,
        )
    }

    /// Writes a shard of `rows` (each N ids, every id below 65536) for `clips`, then records it (replacing
    /// an older record of the same log) and saves the index.
    pub fn add_shard(
        &mut self,
        dir: &Path,
        log: &str,
        clips: Vec<TokenClip>,
        rows: &[Vec<u32>],
    ) -> Result<()> {
        let file = format!("shards/{log}.tok");
        let path = dir.join(&file);
        std::fs::create_dir_all(dir.join("shards")).map_err(io(dir.join("shards")))?;
        let n = self.tokens_per_frame;
        let mut bytes = Vec::with_capacity(HEADER as usize + rows.len() * n * 2);
        bytes.extend_from_slice(MAGIC);
        bytes.extend_from_slice(&(n as u32).to_le_bytes());
        bytes.extend_from_slice(&0u32.to_le_bytes());
        bytes.extend_from_slice(&(rows.len() as u64).to_le_bytes());
        bytes.resize(HEADER as usize, 0);
        for (r, row) in rows.iter().enumerate() {
            if row.len() != n {
                return Err(corrupt(
                    &path,
                    format!("row {r} has {} ids, the layout has {n}", row.len()),
                ));
            }
            for &id in row {
                let id = u16::try_from(id)
                    .map_err(|_| corrupt(&path, format!("row {r}: id {id} does not fit 16 bits")))?;
                bytes.extend_from_slice(&id.to_le_bytes());
            }
        }
        write_atomic(&path, &bytes)?;
        self.shards.retain(|s| s.log != log);
        self.shards.push(TokenShard {
            log: log.into(),
            file,
            rows: rows.len(),
            sha256: sha256(&bytes),
            clips,
        });
        self.save(dir)
    }
}

/// An open token cache.
#[derive(Debug)]
pub struct TokenSet {
    dir: PathBuf,
    index: TokenIndex,
    files: Vec<File>,
    clips: Vec<(usize, TokenClip)>,
}

impl TokenSet {
    /// Opens a cache made for layout `fingerprint`, checking every shard's size and checksum.
    pub fn open(dir: &Path, fingerprint: &str) -> Result<Self> {
        let index = TokenIndex::load(dir)?.ok_or_else(|| DataError::Request {
            path: dir.into(),
            message: "no tokens.json: run `umgen tokenize` first".into(),
        })?;
        if index.fingerprint != fingerprint {
            return Err(DataError::Request {
                path: dir.into(),
                message: format!(
                    "tokens were made for layout {}…, this run's layout is {}…",
                    &index.fingerprint[..12.min(index.fingerprint.len())],
                    &fingerprint[..12.min(fingerprint.len())]
                ),
            });
        }
        let mut files = Vec::new();
        let mut clips = Vec::new();
        for (s, shard) in index.shards.iter().enumerate() {
            let path = dir.join(&shard.file);
            let bytes = std::fs::read(&path).map_err(io(&path))?;
            let want = HEADER as usize + shard.rows * index.tokens_per_frame * 2;
            if bytes.len() != want || &bytes[..8] != MAGIC {
                return Err(corrupt(&path, format!("{} bytes, expected {want}", bytes.len())));
            }
            if sha256(&bytes) != shard.sha256 {
                return Err(corrupt(&path, "checksum mismatch"));
            }
            files.push(File::open(&path).map_err(io(&path))?);
            clips.extend(shard.clips.iter().map(|c| (s, c.clone())));
        }
        Ok(Self {
            dir: dir.into(),
            index,
            files,
            clips,
        })
    }

    /// The index.
    pub fn index(&self) -> &TokenIndex {
        &self.index
    }

    /// Clips, in shard order.
    pub fn clips(&self) -> impl Iterator<Item = &TokenClip> {
        self.clips.iter().map(|(_, c)| c)
    }

    /// Every window of `frames` frames at `gap` in clips of `split` (all when `None`).
    pub fn windows(&self, frames: usize, gap: usize, split: Option<&str>) -> Vec<Window> {
        let span = frames.saturating_sub(1) * gap.max(1);
        let mut out = Vec::new();
        for (i, (_, c)) in self.clips.iter().enumerate() {
            if split.is_some_and(|s| s != c.split) || frames == 0 || c.frames <= span {
                continue;
            }
            out.extend((0..c.frames - span).map(|start| Window { clip: i, start }));
        }
        out
    }

    /// The rows of a window, `frames × N` ids.
    pub fn read(&self, w: Window, frames: usize, gap: usize) -> Result<Vec<u32>> {
        let (shard, clip) = self.clips.get(w.clip).ok_or_else(|| DataError::Request {
            path: self.dir.clone(),
            message: format!("no clip {}", w.clip),
        })?;
        if frames == 0 || w.start + (frames - 1) * gap.max(1) >= clip.frames {
            return Err(DataError::Request {
                path: self.dir.clone(),
                message: format!("window past the end of clip `{}`", clip.id),
            });
        }
        let n = self.index.tokens_per_frame;
        let mut out = Vec::with_capacity(frames * n);
        let mut buf = vec![0u8; n * 2];
        let path = self.dir.join(&self.index.shards[*shard].file);
        for i in 0..frames {
            let row = clip.start + w.start + i * gap.max(1);
            self.files[*shard]
                .read_exact_at(&mut buf, HEADER + (row * n * 2) as u64)
                .map_err(io(&path))?;
            out.extend(
                buf.chunks_exact(2)
                    .map(|b| u32::from(u16::from_le_bytes([b[0], b[1]]))),
            );
        }
        Ok(out)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn shards_round_trip_and_damage_is_caught() {
        let dir = tempfile::tempdir().unwrap();
        let mut idx = TokenIndex::new("abc", 3, 0.5);
        let rows: Vec<Vec<u32>> = (0..5).map(|r| vec![r, r + 100, 8193]).collect();
        let clips = vec![
            TokenClip {
                id: "a".into(),
                split: "train".into(),
                start: 0,
                frames: 2,
            },
            TokenClip {
                id: "b".into(),
                split: "test".into(),
                start: 2,
                frames: 3,
            },
        ];
        idx.add_shard(dir.path(), "log1", clips, &rows).unwrap();
        let set = TokenSet::open(dir.path(), "abc").unwrap();
        assert_eq!(set.windows(2, 1, None).len(), 1 + 2);
        assert_eq!(
            set.windows(2, 1, Some("test")),
            vec![Window { clip: 1, start: 0 }, Window { clip: 1, start: 1 }]
        );
        assert_eq!(
            set.read(Window { clip: 1, start: 0 }, 2, 2).unwrap(),
            vec![2, 102, 8193, 4, 104, 8193]
        );
        assert!(set.read(Window { clip: 1, start: 1 }, 2, 2).is_err());
        assert!(
            TokenSet::open(dir.path(), "xyz")
                .unwrap_err()
                .to_string()
                .contains("layout")
        );
        let p = dir.path().join("shards/log1.tok");
        let mut b = std::fs::read(&p).unwrap();
        b[70] ^= 1;
        std::fs::write(&p, b).unwrap();
        let err = TokenSet::open(dir.path(), "abc").unwrap_err().to_string();
        assert!(err.contains("log1.tok") && err.contains("checksum"), "{err}");
        assert!(
            idx.add_shard(dir.path(), "log2", vec![], &[vec![1, 2, 70000]])
                .unwrap_err()
                .to_string()
                .contains("16 bits")
        );
    }
}
