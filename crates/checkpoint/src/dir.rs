//! Checkpoint directories: `<root>/step-000123/` with a checksummed manifest, written atomically.

use crate::error::{CheckpointError, Result, io};
use serde::{Deserialize, Serialize};
use sha2::{Digest, Sha256};
use std::collections::BTreeMap;
use std::io::Write;
use std::path::{Path, PathBuf};

/// Name of the file pointing at the newest checkpoint.
pub const LATEST: &str = "latest";
/// Name of the manifest inside a checkpoint directory.
pub const MANIFEST: &str = "manifest.json";

/// A file of a checkpoint: size and SHA-256.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct FileEntry {
    /// Bytes.
    pub bytes: u64,
    /// Hex SHA-256.
    pub sha256: String,
}

/// What a checkpoint holds, written last so that a checkpoint without it is known to be incomplete.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Manifest {
    /// Always `umgen-checkpoint`.
    pub format: String,
    /// Format version (1).
    pub version: u32,
    /// What was trained (`backbone`, `tokenizer`, …).
    pub kind: String,
    /// Optimisation step.
    pub step: u64,
    /// umgen version that wrote it.
    pub umgen: String,
    /// Seconds since the Unix epoch.
    pub created: u64,
    /// Free-form metadata (resolved config, layout fingerprint, trainer state).
    pub meta: serde_json::Value,
    /// The files and their checksums.
    pub files: BTreeMap<String, FileEntry>,
}

/// A loaded, verified checkpoint.
#[derive(Debug, Clone)]
pub struct Loaded {
    /// Its directory.
    pub dir: PathBuf,
    /// Its manifest.
    pub manifest: Manifest,
    /// File contents by name.
    pub files: BTreeMap<String, Vec<u8>>,
}

impl Loaded {
    /// A file's contents, or an error naming the checkpoint.
    pub fn file(&self, name: &str) -> Result<&[u8]> {
        self.files
            .get(name)
            .map(Vec::as_slice)
            .ok_or_else(|| CheckpointError::Corrupt {
                path: self.dir.clone(),
                reason: format!("has no file `{name}`"),
            })
    }
}

/// Lower-case hex SHA-256 of `data` (file checksums, run identities).
pub fn sha256(data: &[u8]) -> String {
    Sha256::digest(data).iter().map(|b| format!("{b:02x}")).collect()
}

/// The checkpoints of one run.
#[derive(Debug, Clone)]
pub struct CheckpointDir {
    root: PathBuf,
    keep: usize,
}

impl CheckpointDir {
    /// Checkpoints under `root`, keeping the newest `keep` (at least 1).
    pub fn new(root: impl Into<PathBuf>, keep: usize) -> Self {
        Self {
            root: root.into(),
            keep: keep.max(1),
        }
    }

    /// The directory.
    pub fn root(&self) -> &Path {
        &self.root
    }

    /// Writes a checkpoint for `step`: files into a temporary directory, fsynced, then the manifest, then
    /// one rename; then `latest` is replaced atomically and older checkpoints beyond `keep` are removed.
    /// A kill at any point leaves earlier checkpoints intact.
    pub fn save(
        &self,
        kind: &str,
        step: u64,
        meta: serde_json::Value,
        files: &[(&str, &[u8])],
    ) -> Result<PathBuf> {
        std::fs::create_dir_all(&self.root).map_err(io(&self.root))?;
        let name = format!("step-{step:09}");
        let tmp = self.root.join(format!(".{name}.tmp-{}", std::process::id()));
        if tmp.exists() {
            std::fs::remove_dir_all(&tmp).map_err(io(&tmp))?;
        }
        std::fs::create_dir_all(&tmp).map_err(io(&tmp))?;
        let mut entries = BTreeMap::new();
        for (file, data) in files {
            write_synced(&tmp.join(file), data)?;
            entries.insert(
                file.to_string(),
                FileEntry {
                    bytes: data.len() as u64,
                    sha256: sha256(data),
                },
            );
        }
        let manifest = Manifest {
            format: "umgen-checkpoint".into(),
            version: 1,
            kind: kind.into(),
            step,
            umgen: env!("CARGO_PKG_VERSION").into(),
            created: std::time::SystemTime::now()
                .duration_since(std::time::UNIX_EPOCH)
                .map_or(0, |d| d.as_secs()),
            meta,
            files: entries,
        };
        let text = serde_json::to_vec_pretty(&manifest).map_err(|e| CheckpointError::Corrupt {
            path: tmp.clone(),
            reason: e.to_string(),
        })?;
        write_synced(&tmp.join(MANIFEST), &text)?;
        let dest = self.root.join(&name);
        if dest.exists() {
            // Never deleted: a checkpoint of this step that did not verify stays for the user to inspect.
            let aside = self.set_aside(&dest)?;
            tracing::warn!("{} existed already: moved to {}", dest.display(), aside.display());
        }
        std::fs::rename(&tmp, &dest).map_err(io(&dest))?;
        let latest_tmp = self.root.join(format!(".{LATEST}.tmp-{}", std::process::id()));
        write_synced(&latest_tmp, name.as_bytes())?;
        std::fs::rename(&latest_tmp, self.root.join(LATEST)).map_err(io(self.root.join(LATEST)))?;
        self.prune()?;
        Ok(dest)
    }

    /// Checkpoint directories present, oldest first.
    pub fn list(&self) -> Result<Vec<(u64, PathBuf)>> {
        let Ok(rd) = std::fs::read_dir(&self.root) else {
            return Ok(Vec::new());
        };
        let mut out = Vec::new();
        for e in rd {
            let e = e.map_err(io(&self.root))?;
            let name = e.file_name().to_string_lossy().into_owned();
            if let Some(step) = name.strip_prefix("step-").and_then(|s| s.parse::<u64>().ok()) {
                out.push((step, e.path()));
            }
        }
        out.sort();
        Ok(out)
    }

    fn prune(&self) -> Result<()> {
        let all = self.list()?;
        for (_, dir) in all.iter().take(all.len().saturating_sub(self.keep)) {
            std::fs::remove_dir_all(dir).map_err(io(dir))?;
        }
        Ok(())
    }

    /// The checkpoint of the highest step that verifies; damaged newer ones are reported in the log and
    /// passed over. `None` when there is no checkpoint at all; an error naming every checkpoint and why it
    /// does not verify when there are some but none does. (`latest` only says what was written last: a
    /// kill between a checkpoint's rename and `latest`'s leaves a complete newer checkpoint, which wins.)
    pub fn load_latest(&self) -> Result<Option<Loaded>> {
        let candidates = self.list()?;
        if candidates.is_empty() {
            return Ok(None);
        }
        let mut reasons = Vec::new();
        for (_, dir) in candidates.iter().rev() {
            match load(dir) {
                Ok(l) => {
                    for r in &reasons {
                        tracing::warn!("passing over a damaged checkpoint: {r}");
                    }
                    return Ok(Some(l));
                }
                Err(e) => reasons.push(e.to_string()),
            }
        }
        Err(CheckpointError::NoneReadable {
            root: self.root.clone(),
            reasons,
        })
    }

    /// Moves every checkpoint of a step above `step` out of the way (`step-…​.damaged`, or
    /// `.damaged-2`, … if taken), so that a run resumed from `step` neither overwrites nor prunes in
    /// favour of them; their paths after the move. A resumed run calls it once it has loaded `step`, when
    /// every newer checkpoint has failed to verify.
    pub fn set_aside_newer(&self, step: u64) -> Result<Vec<PathBuf>> {
        let mut moved = Vec::new();
        for (s, dir) in self.list()? {
            if s > step {
                moved.push(self.set_aside(&dir)?);
            }
        }
        Ok(moved)
    }

    fn set_aside(&self, dir: &Path) -> Result<PathBuf> {
        let name = dir
            .file_name()
            .map_or_else(String::new, |n| n.to_string_lossy().into_owned());
        let mut to = self.root.join(format!("{name}.damaged"));
        let mut n = 2;
        while to.exists() {
            to = self.root.join(format!("{name}.damaged-{n}"));
            n += 1;
        }
        std::fs::rename(dir, &to).map_err(io(&to))?;
        Ok(to)
    }

    /// Removes what interrupted saves left (`.step-….tmp-PID` directories, `.latest.tmp-PID` files) and
    /// returns each with its size in bytes. Call it when a run starts in this directory: no save of
    /// another process may be under way in it then.
    pub fn remove_stale_temporaries(&self) -> Result<Vec<(PathBuf, u64)>> {
        let Ok(rd) = std::fs::read_dir(&self.root) else {
            return Ok(Vec::new());
        };
        let mut removed = Vec::new();
        for e in rd {
            let e = e.map_err(io(&self.root))?;
            let name = e.file_name().to_string_lossy().into_owned();
            let stale = (name.starts_with(".step-") || name.starts_with(&format!(".{LATEST}.")))
                && name.contains(".tmp-");
            if !stale {
                continue;
            }
            let path = e.path();
            let bytes = size_of(&path);
            if path.is_dir() {
                std::fs::remove_dir_all(&path).map_err(io(&path))?;
            } else {
                std::fs::remove_file(&path).map_err(io(&path))?;
            }
            removed.push((path, bytes));
        }
        removed.sort();
        Ok(removed)
    }
}

/// Bytes under `path` (0 where unreadable: only reported).
fn size_of(path: &Path) -> u64 {
    match std::fs::read_dir(path) {
        Ok(rd) => rd.flatten().map(|e| size_of(&e.path())).sum(),
        Err(_) => std::fs::metadata(path).map_or(0, |m| m.len()),
    }
}

/// Loads one checkpoint directory, verifying every file's size and checksum.
pub fn load(dir: &Path) -> Result<Loaded> {
    let corrupt = |reason: String| CheckpointError::Corrupt {
        path: dir.into(),
        reason,
    };
    let text = std::fs::read(dir.join(MANIFEST))
        .map_err(|e| corrupt(format!("no readable manifest ({e}); an interrupted save?")))?;
    let manifest: Manifest = serde_json::from_slice(&text).map_err(|e| corrupt(format!("manifest: {e}")))?;
    if manifest.format != "umgen-checkpoint" || manifest.version != 1 {
        return Err(corrupt(format!(
            "format {} v{} is not umgen-checkpoint v1",
            manifest.format, manifest.version
        )));
    }
    let mut files = BTreeMap::new();
    for (name, entry) in &manifest.files {
        let data = std::fs::read(dir.join(name)).map_err(|e| corrupt(format!("file `{name}`: {e}")))?;
        if data.len() as u64 != entry.bytes || sha256(&data) != entry.sha256 {
            return Err(corrupt(format!("file `{name}` fails its checksum")));
        }
        files.insert(name.clone(), data);
    }
    Ok(Loaded {
        dir: dir.into(),
        manifest,
        files,
    })
}

fn write_synced(path: &Path, data: &[u8]) -> Result<()> {
    let mut f = std::fs::File::create(path).map_err(io(path))?;
    f.write_all(data).and_then(|()| f.sync_all()).map_err(io(path))
}

#[cfg(test)]
#[path = "dir_tests.rs"]
mod tests;
