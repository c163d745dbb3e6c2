//! `umgen-kernel-bench train --host-profile FILE …`: where the host's threads spend their time over the timed
//! steps (the training thread, burn-fusion's and cubecl's device threads), for machines without `perf`.
//! Builds with the `host-profile` feature sample every thread's stack about 1,000 times a second of CPU time
//! (SIGPROF, `pprof`) and write the samples as collapsed stacks (`thread;outer;…;inner count`, one line a
//! stack, the format flame-graph tools read). The binary needs its symbols: build with
//! `CARGO_PROFILE_RELEASE_STRIP=false`.

use std::path::PathBuf;

/// The profile being taken, if a file was given.
pub(super) struct HostProfile {
    #[cfg(feature = "host-profile")]
    taking: Option<(pprof::ProfilerGuard<'static>, PathBuf)>,
}

impl HostProfile {
    /// Starts sampling into `path` when given (a build without `host-profile` says so and samples
    /// nothing).
    pub(super) fn start(path: Option<PathBuf>) -> anyhow::Result<Self> {
        #[cfg(feature = "host-profile")]
        {
            let taking = match path {
                Some(path) => {
                    // Unwinding through these while they hold locks can deadlock the sampled thread.
                    let guard = pprof::ProfilerGuardBuilder::default()
                        .frequency(997)
                        .blocklist(&["libc", "libgcc", "pthread", "vdso"])
                        .build()
                        .map_err(|e| anyhow::anyhow!("--host-profile: starting the sampler: {e}"))?;
                    Some((guard, path))
                }
                None => None,
            };
            Ok(Self { taking })
        }
        #[cfg(not(feature = "host-profile"))]
        {
            if let Some(path) = path {
                tracing::warn!(
                    "--host-profile {} is ignored: this build lacks the host-profile feature",
                    path.display()
                );
            }
            Ok(Self {})
        }
    }

    /// Writes the collapsed stacks, if a profile was taken.
    pub(super) fn finish(self) -> anyhow::Result<()> {
        #[cfg(feature = "host-profile")]
        if let Some((guard, path)) = self.taking {
            use std::fmt::Write as _;
            let report = guard
                .report()
                .build()
                .map_err(|e| anyhow::anyhow!("--host-profile: building the report: {e}"))?;
            let mut out = String::new();
            for (frames, count) in &report.data {
                let mut line = frames.thread_name_or_id();
                // pprof lists the innermost frame first.
                for symbol in frames.frames.iter().rev().flatten() {
                    line.push(';');
                    line.push_str(&symbol.name().replace(';', ":"));
                }
                let _ = writeln!(out, "{line} {count}");
            }
            std::fs::write(&path, out)
                .map_err(|e| anyhow::anyhow!("--host-profile: writing {}: {e}", path.display()))?;
            tracing::info!("host profile: {} stacks in {}", report.data.len(), path.display());
        }
        Ok(())
    }
}
