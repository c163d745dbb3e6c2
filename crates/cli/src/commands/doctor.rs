//! `umgen doctor`: what this machine offers for GPU runs, and how to fix what is missing.

use std::io::Write;

/// Prints one line per check; fails when a check that GPU runs need fails.
pub fn run() -> anyhow::Result<()> {
    let mut out = std::io::stdout().lock();
    writeln!(out, "umgen {}", env!("CARGO_PKG_VERSION"))?;
    let problems = gpu::check(&mut out)?;
    out.flush()?;
    if problems > 0 {
        anyhow::bail!("{problems} check(s) failed; GPU runs will not work until they pass");
    }
    Ok(())
}

#[cfg(not(feature = "cuda"))]
mod gpu {
    use std::io::Write;

    pub fn check(out: &mut impl Write) -> anyhow::Result<usize> {
        writeln!(
            out,
            "cuda     not built in: rebuild with `cargo build --release --features cuda` for GPU runs"
        )?;
        writeln!(
            out,
            "cpu      available ({} threads)",
            std::thread::available_parallelism().map_or(1, |n| n.get())
        )?;
        Ok(0)
    }
}

#[cfg(feature = "cuda")]
#[allow(unsafe_code)]
mod gpu {
    use cudarc::driver::CudaContext;
    use std::io::Write;
    use std::path::Path;

    pub fn check(out: &mut impl Write) -> anyhow::Result<usize> {
        let mut problems = 0;
        // SAFETY: `is_culib_present` only tries to dlopen the library; it has no preconditions.
        let driver = unsafe { cudarc::driver::sys::is_culib_present() };
        if driver {
            match CudaContext::device_count() {
                Ok(n) => {
                    writeln!(out, "driver   ok, {n} device(s)")?;
                    for i in 0..n {
                        let ctx = CudaContext::new(i as usize)?;
                        let gib = ctx.total_mem()? as f64 / (1u64 << 30) as f64;
                        writeln!(out, "  cuda:{i}  {} ({gib:.1} GiB)", ctx.name()?)?;
                    }
                }
                Err(e) => {
                    problems += 1;
                    writeln!(out, "driver   loaded but not usable: {e}")?;
                }
            }
        } else {
            problems += 1;
            writeln!(
                out,
                "driver   MISSING: libcuda.so.1 is not loadable (is the NVIDIA driver installed?)"
            )?;
        }
        // SAFETY: as above.
        if unsafe { cudarc::nvrtc::sys::is_culib_present() } {
            writeln!(out, "nvrtc    ok")?;
        } else {
            problems += 1;
            writeln!(
                out,
                "nvrtc    MISSING: put the CUDA toolkit's targets/x86_64-linux/lib on LD_LIBRARY_PATH"
            )?;
        }
        let roots = [
            std::env::var("CUDA_PATH").ok(),
            Some("/usr/local/cuda".into()),
            Some("/opt/cuda".into()),
        ];
        match roots
            .into_iter()
            .flatten()
            .find(|r| Path::new(r).join("include/cuda.h").exists())
        {
            Some(root) => writeln!(
                out,
                "headers  ok ({root}/include; NVRTC compiles kernels against them)"
            )?,
            None => {
                problems += 1;
                writeln!(
                    out,
                    "headers  MISSING: set CUDA_PATH to the CUDA toolkit (it needs include/cuda.h)"
                )?;
            }
        }
        // SAFETY: as above.
        if unsafe { cudarc::nccl::sys::is_culib_present() } {
            let v =
                cudarc::nccl::result::get_nccl_version().map_or_else(|e| format!("{e:?}"), |v| v.to_string());
            writeln!(out, "nccl     ok (version code {v})")?;
        } else {
            problems += 1;
            writeln!(
                out,
                "nccl     MISSING: cudarc loads `libnccl.so`; link libnccl.so.2 under that name into a folder on \
                 LD_LIBRARY_PATH (launchers/gpu-env.sh does this)"
            )?;
        }
        match umgen_cuda::kernel_cache_dir() {
            Some(dir) => writeln!(
                out,
                "kernels  compiled CUDA kernels kept in {} (UMGEN_KERNEL_CACHE=DIR moves it, =off disables; a \
                 cubecl.toml that sets a compilation cache wins)",
                dir.display()
            )?,
            None => writeln!(
                out,
                "kernels  not kept between runs (UMGEN_KERNEL_CACHE=off, or no home directory)"
            )?,
        }
        // `run_main` applied UMGEN_MEMORY_POOL before this command (refusing a bad value); the layout in
        // effect can differ from the variable's (cubecl's own in a build without the patched cubecl-cuda).
        let layout = crate::memory_pool::applied().unwrap_or(crate::memory_pool::PoolLayout::Cubecl);
        writeln!(
            out,
            "memory   pool layout {layout} (UMGEN_MEMORY_POOL=pages:MIB sets the largest shared page, =cubecl \
             cubecl's own layout)"
        )?;
        if cfg!(feature = "autotune") {
            writeln!(
                out,
                "autotune on: matmuls, convolutions and fused kernels are timed per shape on first use (minutes \
                 per process; docs/performance.md)"
            )?;
        } else {
            writeln!(
                out,
                "autotune off: burn's default kernels (build with `--features autotune` to time candidates)"
            )?;
        }
        Ok(problems)
    }
}
