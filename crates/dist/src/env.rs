//! Who this process is: rank, world size and rendezvous address from the torchrun variables or from SLURM.

use crate::error::{DistError, Result};

/// The default rendezvous port (torchrun's).
pub const DEFAULT_PORT: u16 = 29500;

/// This process's place in the job.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct DistEnv {
    /// Global rank, `0..world_size`.
    pub rank: usize,
    /// Number of processes.
    pub world_size: usize,
    /// Rank on this node; picks the GPU.
    pub local_rank: usize,
    /// Processes on this node.
    pub local_world_size: usize,
    /// Host of rank 0's rendezvous.
    pub master_addr: String,
    /// Port of rank 0's rendezvous.
    pub master_port: u16,
    /// Where the values came from: `torchrun`, `slurm` or `single`.
    pub source: &'static str,
}

impl DistEnv {
    /// One process, no peers.
    pub fn single() -> Self {
        Self {
            rank: 0,
            world_size: 1,
            local_rank: 0,
            local_world_size: 1,
            master_addr: "127.0.0.1".into(),
            master_port: DEFAULT_PORT,
            source: "single",
        }
    }

    /// From this process's environment.
    pub fn from_env() -> Result<Self> {
        Self::from_vars(|k| std::env::var(k).ok())
    }

    /// From variables looked up by `get`: torchrun's `RANK`/`WORLD_SIZE` win over SLURM's
    /// `SLURM_PROCID`/`SLURM_NTASKS`; neither means a single process.
    pub fn from_vars(get: impl Fn(&str) -> Option<String>) -> Result<Self> {
        let num = |var: &str, default: Option<usize>| -> Result<usize> {
            match get(var) {
                Some(v) => v.trim().parse().map_err(|_| DistError::Env {
                    var: var.into(),
                    value: v.clone(),
                    reason: "not a non-negative integer".into(),
                }),
                None => default.ok_or_else(|| DistError::Env {
                    var: var.into(),
                    value: String::new(),
                    reason: "not set".into(),
                }),
            }
        };
        let env = if get("RANK").is_some() || get("WORLD_SIZE").is_some() {
            let rank = num("RANK", None)?;
            let world_size = num("WORLD_SIZE", None)?;
            Self {
                rank,
                world_size,
                local_rank: num("LOCAL_RANK", Some(rank))?,
                local_world_size: num("LOCAL_WORLD_SIZE", Some(world_size))?,
                master_addr: get("MASTER_ADDR").unwrap_or_else(|| "127.0.0.1".into()),
                master_port: port(&get, None)?,
                source: "torchrun",
            }
        } else if get("SLURM_PROCID").is_some() {
            let rank = num("SLURM_PROCID", None)?;
            let world_size = num("SLURM_NTASKS", None)?;
            let master_addr = match get("MASTER_ADDR") {
                Some(a) => a,
                None => {
                    let var = if get("SLURM_JOB_NODELIST").is_some() {
                        "SLURM_JOB_NODELIST"
                    } else {
                        "SLURM_NODELIST"
                    };
                    let list = get(var).unwrap_or_default();
                    first_host(&list).ok_or_else(|| DistError::Env {
                        var: var.into(),
                        value: list.clone(),
                        reason: "no host in the node list (set MASTER_ADDR)".into(),
                    })?
                }
            };
            let job = get("SLURM_JOB_ID").and_then(|j| j.parse::<u64>().ok());
            // Jobs sharing a node get different ports; the range avoids well-known and ephemeral ports.
            let from_job = job.map(|j| 20000 + (j % 10000) as u16);
            Self {
                rank,
                world_size,
                local_rank: num("SLURM_LOCALID", Some(0))?,
                local_world_size: get("SLURM_NTASKS_PER_NODE")
                    .or_else(|| get("SLURM_TASKS_PER_NODE"))
                    .and_then(|v| leading_number(&v))
                    .unwrap_or(world_size),
                master_addr,
                master_port: port(&get, from_job)?,
                source: "slurm",
            }
        } else {
            return Ok(Self::single());
        };
        let bad = |var: &str, value: usize, reason: String| DistError::Env {
            var: var.into(),
            value: value.to_string(),
            reason,
        };
        if env.world_size == 0 {
            return Err(bad("WORLD_SIZE", 0, "must be at least 1".into()));
        }
        if env.rank >= env.world_size {
            return Err(bad(
                "RANK",
                env.rank,
                format!("must be below the world size {}", env.world_size),
            ));
        }
        if env.local_rank >= env.local_world_size.max(1) {
            return Err(bad(
                "LOCAL_RANK",
                env.local_rank,
                format!("must be below the local world size {}", env.local_world_size),
            ));
        }
        Ok(env)
    }

    /// `MASTER_ADDR:MASTER_PORT`.
    pub fn master(&self) -> String {
        format!("{}:{}", self.master_addr, self.master_port)
    }

    /// The variables a launcher sets for `rank` of this job (the torchrun contract).
    pub fn vars(&self) -> Vec<(&'static str, String)> {
        vec![
            ("RANK", self.rank.to_string()),
            ("WORLD_SIZE", self.world_size.to_string()),
            ("LOCAL_RANK", self.local_rank.to_string()),
            ("LOCAL_WORLD_SIZE", self.local_world_size.to_string()),
            ("MASTER_ADDR", self.master_addr.clone()),
            ("MASTER_PORT", self.master_port.to_string()),
        ]
    }
}

fn port(get: &impl Fn(&str) -> Option<String>, fallback: Option<u16>) -> Result<u16> {
    match get("MASTER_PORT") {
        Some(v) => v
            .trim()
            .parse::<u16>()
            .ok()
            .filter(|p| *p > 0)
            .ok_or_else(|| DistError::Env {
                var: "MASTER_PORT".into(),
                value: v.clone(),
                reason: "not a port number (1-65535)".into(),
            }),
        None => Ok(fallback.unwrap_or(DEFAULT_PORT)),
    }
}

fn leading_number(s: &str) -> Option<usize> {
    let digits: String = s.chars().take_while(char::is_ascii_digit).collect();
    digits.parse().ok()
}

/// The first host of a SLURM node list: `gpu[003-005,9],login1` → `gpu003`.
pub fn first_host(list: &str) -> Option<String> {
    let list = list.trim();
    let mut depth = 0;
    let end = list
        .char_indices()
        .find(|&(_, c)| {
            match c {
                '[' => depth += 1,
                ']' => depth -= 1,
                _ => {}
            }
            c == ',' && depth == 0
        })
        .map_or(list.len(), |(i, _)| i);
    let first = &list[..end];
    let host = match first.split_once('[') {
        None => first.to_string(),
        Some((prefix, rest)) => {
            let inner = rest.split(']').next()?;
            let range = inner.split(',').next()?;
            let start = range.split('-').next()?;
            let suffix = rest.split_once(']').map_or("", |(_, s)| s);
            format!("{prefix}{start}{suffix}")
        }
    };
    (!host.is_empty()).then_some(host)
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]
    use super::*;
    use std::collections::HashMap;

    fn env(pairs: &[(&str, &str)]) -> Result<DistEnv> {
        let m: HashMap<String, String> = pairs
            .iter()
            .map(|(k, v)| (k.to_string(), v.to_string()))
            .collect();
        DistEnv::from_vars(|k| m.get(k).cloned())
    }

    #[test]
    fn torchrun_slurm_and_single() {
        assert_eq!(env(&[]).unwrap(), DistEnv::single());
        let t = env(&[
            ("RANK", "3"),
            ("WORLD_SIZE", "8"),
            ("LOCAL_RANK", "1"),
            ("LOCAL_WORLD_SIZE", "2"),
            ("MASTER_ADDR", "node7"),
            ("MASTER_PORT", "1234"),
        ])
        .unwrap();
        assert_eq!(
            (t.rank, t.world_size, t.local_rank, t.master(), t.source),
            (3, 8, 1, "node7:1234".into(), "torchrun")
        );
        let s = env(&[
            ("SLURM_PROCID", "5"),
            ("SLURM_NTASKS", "16"),
            ("SLURM_LOCALID", "1"),
            ("SLURM_TASKS_PER_NODE", "4(x4)"),
            ("SLURM_JOB_NODELIST", "gpu[007-010],cpu1"),
            ("SLURM_JOB_ID", "123456"),
        ])
        .unwrap();
        assert_eq!(
            (s.rank, s.world_size, s.local_rank, s.local_world_size),
            (5, 16, 1, 4)
        );
        assert_eq!(s.master(), "gpu007:23456");
    }

    #[test]
    fn bad_values_name_the_variable() {
        let e = env(&[("RANK", "2"), ("WORLD_SIZE", "2")])
            .unwrap_err()
            .to_string();
        assert!(e.contains("RANK=\"2\"") && e.contains("world size 2"), "{e}");
        let e = env(&[("RANK", "0"), ("WORLD_SIZE", "two")])
            .unwrap_err()
            .to_string();
        assert!(e.contains("WORLD_SIZE=\"two\""), "{e}");
        let e = env(&[("RANK", "0"), ("WORLD_SIZE", "2"), ("MASTER_PORT", "70000")])
            .unwrap_err()
            .to_string();
        assert!(e.contains("MASTER_PORT"), "{e}");
        let e = env(&[("SLURM_PROCID", "0"), ("SLURM_NTASKS", "2")])
            .unwrap_err()
            .to_string();
        assert!(e.contains("SLURM_NODELIST"), "{e}");
    }

    #[test]
    fn node_lists() {
        assert_eq!(first_host("node1,node2").as_deref(), Some("node1"));
        assert_eq!(first_host("nid00[123-125,200]").as_deref(), Some("nid00123"));
        assert_eq!(first_host("a[1,3]-ib,b").as_deref(), Some("a1-ib"));
        assert_eq!(first_host(""), None);
    }
}
