//! The engine's kernels compiled at start-up: each kernel file of [`crate::source::ENGINE_PARTS`] and
//! each of flash2's forward kernels as its own NVRTC program, compiled to machine code (`cubin.rs`, with
//! its cache) and loaded on a thread each, so that the first start on a machine waits for the slowest
//! program rather than for all of them. A GPU whose architecture this build does not name gets PTX, which
//! its driver translates.

use super::{arch, device};
use crate::ops::ExecError;
use cudarc::driver::{CudaContext, CudaFunction};
use cudarc::nvrtc::{CompileOptions, Ptx, compile_ptx_with_opts};
use std::collections::HashMap;
use std::sync::Arc;
use std::time::Instant;

/// The kernels by name.
pub(super) type Kernels = HashMap<&'static str, CudaFunction>;

/// One program: what it is called in errors, its source, its options and the kernels to take from it.
struct Program {
    what: &'static str,
    source: String,
    /// NVRTC's virtual architecture (`compute_XY`), or its default where the device's is not known.
    arch: Option<&'static str>,
    fast_math: bool,
    /// Whether NVRTC makes machine code for the device (`arch` with `sm_` for `compute_`: it must be the
    /// device's own), rather than PTX for the driver to translate.
    machine: bool,
    kernels: &'static [&'static str],
    /// Whether its kernels are flash2's.
    flash2: bool,
}

/// flash2's forward kernels the window pass launches (bf16, head sizes 32 and 64), each its own program.
const FLASH2_FORWARD: [(usize, &[&str]); 2] = [
    (32, &["umgen_flash2_forward_bf16_32"]),
    (64, &["umgen_flash2_forward_bf16_64"]),
];

/// Compiles and loads the engine's kernels for the device of `ctx` (compute capability `major.minor`) with
/// bf16 (`bf16`) or f32 weights: the engine's kernels, and flash2's forward kernels when `bf16` and the
/// device has bf16 tensor cores (compute capability 8.0 or newer).
pub(super) fn kernels(
    ctx: &Arc<CudaContext>,
    (major, minor): (i32, i32),
    bf16: bool,
) -> Result<(Kernels, Option<Kernels>), ExecError> {
    let started = Instant::now();
    let mut programs = Vec::new();
    let dir = std::env::var_os("UMGEN_ENGINE_SOURCE").map(std::path::PathBuf::from);
    for (file, kernels) in crate::source::ENGINE_PARTS {
        let source = match &dir {
            Some(dir) => crate::source::engine_part_from(bf16, file, dir)?,
            None => crate::source::engine_part(bf16, file),
        }
        .ok_or_else(|| ExecError::Invalid(format!("no engine source {file}")))?;
        let arch = arch(major, minor);
        programs.push(Program {
            what: file,
            source,
            arch,
            fast_math: false,
            machine: arch.is_some(),
            kernels,
            flash2: false,
        });
    }
    let flash = bf16 && major >= 8;
    if flash {
        // As the training compiles them: Hopper's `wgmma` for head size 64 on sm_90a.
        for (dh, kernels) in FLASH2_FORWARD {
            programs.push(Program {
                what: if dh == 32 { "flash2 (32)" } else { "flash2 (64)" },
                source: crate::source::flash2_forward_bf16(dh),
                arch: Some(if major == 9 { "compute_90a" } else { "compute_80" }),
                fast_math: true,
                // Other architectures keep compute_80's code, which only PTX can carry to them.
                machine: major == 9,
                kernels,
                flash2: true,
            });
        }
    }
    let loaded: Vec<(bool, Result<Kernels, ExecError>)> = std::thread::scope(|s| {
        let handles: Vec<_> = programs
            .into_iter()
            .map(|p| (p.flash2, s.spawn(move || load(ctx, p))))
            .collect();
        handles
            .into_iter()
            .map(|(flash2, h)| {
                let loaded = h.join().unwrap_or_else(|_| {
                    Err(ExecError::Device("a kernel compilation thread panicked".into()))
                });
                (flash2, loaded)
            })
            .collect()
    });
    let mut engine = HashMap::new();
    let mut flash2 = HashMap::new();
    for (is_flash2, kernels) in loaded {
        if is_flash2 { &mut flash2 } else { &mut engine }.extend(kernels?);
    }
    tracing::info!(
        "engine kernels compiled for sm_{major}{minor} ({}) in {:.1} s",
        if bf16 { "bf16" } else { "f32" },
        started.elapsed().as_secs_f64()
    );
    Ok((engine, flash.then_some(flash2)))
}

/// Compiles `p` with NVRTC (or reads its machine code from the cache), loads it into `ctx` and takes its
/// kernels.
fn load(ctx: &Arc<CudaContext>, p: Program) -> Result<Kernels, ExecError> {
    let started = Instant::now();
    let (code, from) = match (p.machine, p.arch) {
        (true, Some(arch)) => {
            let mut options = vec![format!("--gpu-architecture={}", arch.replace("compute_", "sm_"))];
            if p.fast_math {
                options.push("--use_fast_math".into());
            }
            let (cubin, from) = super::cubin::cubin(p.what, &p.source, &options)?;
            let from = match from {
                super::cubin::Source::Cache(path) => format!("machine code from {}", path.display()),
                super::cubin::Source::Compiled => "machine code by NVRTC".to_string(),
            };
            (Ptx::from_binary(cubin), from)
        }
        _ => (
            compile_ptx_with_opts(
                &p.source,
                CompileOptions {
                    arch: p.arch,
                    use_fast_math: p.fast_math.then_some(true),
                    ..Default::default()
                },
            )
            .map_err(|e| device("NVRTC")(format!("{}: {e:?}", p.what)))?,
            "PTX by NVRTC".to_string(),
        ),
    };
    let made = started.elapsed().as_secs_f64();
    let module = ctx
        .load_module(code)
        .map_err(|e| device("loading the kernels")(format!("{}: {e:?}", p.what)))?;
    tracing::debug!(
        "{}: {from} in {made:.1} s, loaded in {:.1} s",
        p.what,
        started.elapsed().as_secs_f64() - made
    );
    let mut found = HashMap::new();
    for &name in p.kernels {
        let f = module
            .load_function(name)
            .map_err(|e| device(name)(format!("{}: {e:?}", p.what)))?;
        found.insert(name, f);
    }
    Ok(found)
}
