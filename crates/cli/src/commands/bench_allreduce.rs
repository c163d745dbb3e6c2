//! `umgen bench allreduce`: the process group's all-reduce bandwidth.

use super::bench_train::median;
use crate::cli::BenchAllreduceArgs;
use crate::device::Device;
use crate::dist::{DistBackend, rank_device};
use anyhow::Context;
use burn::tensor::Tensor;
use burn::tensor::backend::{AutodiffBackend, Backend};
use std::io::Write;
use std::time::Instant;
use umgen::dist::DistEnv;

/// All-reduce (mean) bandwidth through the process group: median time per size, the algorithm bandwidth
/// (bytes / time) and the bus bandwidth (× 2(W−1)/W, what each link carries in a ring; comparable with
/// nccl-tests' `busbw`).
pub fn allreduce(a: &BenchAllreduceArgs) -> anyhow::Result<()> {
    let env = DistEnv::from_env()?;
    let device = Device::parse(&rank_device(&a.device, &env))?;
    let world = env.world_size as f64;
    let rows = crate::with_autodiff!(device, |B, dev| {
        type I = <B as AutodiffBackend>::InnerBackend;
        let mut group = <I as DistBackend>::join(&env, "bench-allreduce", &a.dist)?;
        let mut rows = Vec::new();
        for &mib in &a.mib {
            let n = ((mib * 1048576.0) / 4.0).max(1.0) as usize;
            let t = Tensor::<I, 1>::ones([n], &dev);
            let mut times = Vec::new();
            for i in 0..a.iters + 2 {
                group.barrier()?;
                let t0 = Instant::now();
                let r = group.all_reduce_mean(t.clone())?;
                <I as Backend>::sync(&dev).map_err(|e| anyhow::anyhow!("device sync: {e:?}"))?;
                if i >= 2 {
                    times.push(t0.elapsed().as_secs_f64());
                }
                drop(r);
            }
            let median = median(times).context("--iters 0: give one timed all-reduce or more")?;
            rows.push((mib, median));
        }
        group.barrier()?;
        group.finish();
        (rows, group.backend())
    });
    if env.rank != 0 {
        return Ok(());
    }
    let (rows, backend) = rows;
    let mut out = std::io::stdout().lock();
    writeln!(
        out,
        "all-reduce (mean) over {} ranks, {backend}, {}",
        env.world_size, a.device
    )?;
    writeln!(
        out,
        "{:>10} {:>10} {:>12} {:>12}",
        "MiB", "ms", "algbw GB/s", "busbw GB/s"
    )?;
    for (mib, s) in rows {
        let alg = mib * 1048576.0 / s / 1e9;
        writeln!(
            out,
            "{mib:>10.1} {:>10.3} {alg:>12.2} {:>12.2}",
            1e3 * s,
            alg * 2.0 * (world - 1.0) / world
        )?;
    }
    Ok(())
}
