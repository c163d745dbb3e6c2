//! Joining a data-parallel job: which process group each backend uses, and what a failure does.

use crate::cli::DistArgs;
use burn::tensor::backend::Backend;
use std::sync::Arc;
use std::time::Duration;
use umgen::dist::{DistEnv, ProcessGroup, Session, SessionOptions, Single, TcpGroup};

/// A process group on the tensors of this backend.
pub type BoxedGroup<B> = Box<dyn ProcessGroup<B>>;

/// Backends that can join a job.
pub trait DistBackend: Backend {
    /// Meets the other ranks of `env` and returns the group (a [`Single`] group without peers).
    fn join(env: &DistEnv, identity: &str, args: &DistArgs) -> anyhow::Result<BoxedGroup<Self>>;
}

fn options(args: &DistArgs) -> SessionOptions {
    SessionOptions {
        timeout: Duration::from_secs(args.dist_timeout.max(1)),
        // The watchdog has logged the reason. A TCP collective has already failed (its sockets are shut),
        // letting the command report it; an NCCL collective waiting for a dead peer never returns, so
        // exit after a moment either way.
        on_failure: Arc::new(|_why: &str| {
            std::thread::sleep(Duration::from_secs(3));
            std::process::exit(1);
        }),
    }
}

fn tcp<B: Backend>(env: &DistEnv, identity: &str, args: &DistArgs) -> anyhow::Result<BoxedGroup<B>> {
    let session = Session::connect(env.clone(), identity, &options(args), || Ok(Vec::new()))?;
    Ok(Box::new(TcpGroup::new(session)))
}

impl DistBackend for burn::backend::Flex {
    fn join(env: &DistEnv, identity: &str, args: &DistArgs) -> anyhow::Result<BoxedGroup<Self>> {
        if env.world_size == 1 {
            return Ok(Box::new(Single));
        }
        match args.dist_backend.as_str() {
            "auto" | "tcp" => tcp(env, identity, args),
            other => anyhow::bail!(
                "--dist-backend {other}: the CPU runs collectives over `tcp` (NCCL needs --device cuda)"
            ),
        }
    }
}

#[cfg(feature = "cuda")]
impl DistBackend for burn::backend::Cuda {
    fn join(env: &DistEnv, identity: &str, args: &DistArgs) -> anyhow::Result<BoxedGroup<Self>> {
        if env.world_size == 1 {
            return Ok(Box::new(Single));
        }
        match args.dist_backend.as_str() {
            "tcp" => tcp(env, identity, args),
            "auto" | "nccl" => {
                let rank = env.rank;
                let session = Session::connect(env.clone(), identity, &options(args), || {
                    umgen::dist::nccl_id(rank)
                })?;
                let device = burn::backend::cuda::CudaDevice::new(env.local_rank);
                Ok(Box::new(umgen::dist::NcclGroup::new(session, &device)?))
            }
            other => anyhow::bail!("--dist-backend {other}: expected auto, tcp or nccl"),
        }
    }
}

/// [`DistBackend::join`], saying on rank 0 how the ranks meet when there are several.
pub fn join<B: DistBackend>(env: &DistEnv, identity: &str, args: &DistArgs) -> anyhow::Result<BoxedGroup<B>> {
    let group = B::join(env, identity, args)?;
    if env.world_size > 1 {
        tracing::info!(
            "{} ranks over {} (rendezvous {})",
            env.world_size,
            group.backend(),
            env.master()
        );
    }
    Ok(group)
}

/// The device of this rank: under a launcher, `cuda` means the GPU of `LOCAL_RANK`.
pub fn rank_device(device: &str, env: &DistEnv) -> String {
    if device == "cuda" && env.world_size > 1 {
        format!("cuda:{}", env.local_rank)
    } else {
        device.to_string()
    }
}
