//! `umgen launch`: start this node's ranks with the torchrun variables and supervise them.

use crate::cli::LaunchArgs;
use std::process::{Child, Command, ExitStatus};
use std::time::Duration;
use umgen::dist::DistEnv;

/// Set for the ranks: the launcher's process id.
const LAUNCHER_PID: &str = "UMGEN_LAUNCHER_PID";

/// In a rank started by `umgen launch`: exits when the launcher is gone (killed with SIGKILL, it cannot
/// stop its ranks itself), so that no rank is left training or holding a GPU.
pub fn guard_parent() {
    #[cfg(unix)]
    watch_parent();
}

#[cfg(unix)]
fn watch_parent() {
    let Some(pid) = std::env::var(LAUNCHER_PID)
        .ok()
        .and_then(|p| p.parse::<u32>().ok())
    else {
        return;
    };
    let spawned = std::thread::Builder::new()
        .name("umgen-launcher-guard".into())
        .spawn(move || {
            loop {
                if std::os::unix::process::parent_id() != pid {
                    tracing::error!("the launcher (pid {pid}) is gone; exiting");
                    std::process::exit(1);
                }
                std::thread::sleep(Duration::from_millis(500));
            }
        });
    if let Err(e) = spawned {
        tracing::warn!("cannot watch the launcher: {e}");
    }
}

/// Spawns `nproc_per_node` ranks running `umgen <command>` and waits. When a rank fails, the others are
/// killed (their checkpoints are written atomically, so nothing half-written survives) and the
/// launcher fails with the rank's exit code.
pub fn run(a: &LaunchArgs) -> anyhow::Result<()> {
    anyhow::ensure!(a.nproc_per_node >= 1, "--nproc-per-node must be at least 1");
    anyhow::ensure!(
        a.node_rank < a.nnodes,
        "--node-rank {} must be below --nnodes {}",
        a.node_rank,
        a.nnodes
    );
    let exe = std::env::current_exe()?;
    let world = a.nproc_per_node * a.nnodes;
    let mut children: Vec<(usize, Child)> = Vec::new();
    for local in 0..a.nproc_per_node {
        let env = DistEnv {
            rank: a.node_rank * a.nproc_per_node + local,
            world_size: world,
            local_rank: local,
            local_world_size: a.nproc_per_node,
            master_addr: a.master_addr.clone(),
            master_port: a.master_port,
            source: "torchrun",
        };
        let mut cmd = Command::new(&exe);
        cmd.args(&a.command);
        for (k, v) in env.vars() {
            cmd.env(k, v);
        }
        // Ranks exit when the launcher dies (see `guard_parent`).
        cmd.env(LAUNCHER_PID, std::process::id().to_string());
        // torchrun's habit: one thread pool per rank, not one per core each.
        if std::env::var_os("OMP_NUM_THREADS").is_none() {
            cmd.env("OMP_NUM_THREADS", "1");
        }
        match cmd.spawn() {
            Ok(c) => {
                tracing::info!("started rank {} (pid {})", env.rank, c.id());
                children.push((env.rank, c));
            }
            Err(e) => {
                stop(&mut children);
                anyhow::bail!("starting rank {} ({}): {e}", env.rank, exe.display());
            }
        }
    }
    let mut running = children.len();
    while running > 0 {
        let mut failed: Option<(usize, ExitStatus)> = None;
        running = 0;
        for (rank, c) in &mut children {
            match c.try_wait()? {
                Some(status) if !status.success() => {
                    failed.get_or_insert((*rank, status));
                }
                Some(_) => {}
                None => running += 1,
            }
        }
        if let Some((rank, status)) = failed {
            tracing::error!("rank {rank} failed ({status}); stopping the other ranks");
            stop(&mut children);
            let code = status.code().unwrap_or(1);
            anyhow::bail!("rank {rank} failed with exit code {code}");
        }
        std::thread::sleep(Duration::from_millis(50));
    }
    tracing::info!("all {} ranks finished", children.len());
    Ok(())
}

fn stop(children: &mut [(usize, Child)]) {
    for (_, c) in children.iter_mut() {
        if matches!(c.try_wait(), Ok(None)) {
            let _ = c.kill();
        }
    }
    for (_, c) in children.iter_mut() {
        let _ = c.wait();
    }
}
