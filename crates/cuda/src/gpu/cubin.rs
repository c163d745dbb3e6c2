//! A kernel program's machine code (CUBIN) for one GPU architecture, made by NVRTC on the calling thread
//! and kept in a cache directory.
//!
//! Why not PTX: the driver translates PTX to machine code under a lock of its own, so the engine's
//! programs, compiled side by side, were then translated one after another (6.7 s of a `paper` start on a
//! fresh H200, of which NVRTC took 2.2 s). NVRTC makes the machine code itself, on each program's thread,
//! and the driver only loads it. The driver's own cache of translations does not apply to CUBIN, so this
//! module keeps one in [`crate::kernel_cache_dir`]. An entry is named by a hash of NVRTC's version, the
//! options and the source, so a changed kernel or compiler never reads a stale one; a cache that cannot be
//! read or written only costs the compilation.

use super::device;
use crate::ops::ExecError;
use cudarc::nvrtc::{result as nvrtc, sys as nvrtc_sys};
use std::ffi::{CStr, CString};
use std::path::PathBuf;

/// FNV-1a (64 bits) over `parts`, each followed by a 0 byte so that their boundaries count.
fn fnv1a(parts: &[&[u8]]) -> u64 {
    let mut h = 0xcbf2_9ce4_8422_2325u64;
    for part in parts {
        for &b in part.iter().chain(std::iter::once(&0)) {
            h = (h ^ u64::from(b)).wrapping_mul(0x0100_0000_01b3);
        }
    }
    h
}

/// NVRTC's version, as the cache key's first part.
fn nvrtc_version() -> Result<(i32, i32), ExecError> {
    let (mut major, mut minor) = (0, 0);
    // SAFETY: two valid out-pointers.
    unsafe { nvrtc_sys::nvrtcVersion(&mut major, &mut minor) }
        .result()
        .map_err(|e| device("NVRTC version")(format!("{e:?}")))?;
    Ok((major, minor))
}

/// Where the machine code came from.
pub(super) enum Source {
    /// Read from this cache file.
    Cache(PathBuf),
    /// Compiled now (and written to the cache when it has one).
    Compiled,
}

/// The machine code of `source` under NVRTC `options` (which name a real architecture, `sm_XY`), from the
/// cache or compiled; `what` names the program in errors.
pub(super) fn cubin(what: &str, source: &str, options: &[String]) -> Result<(Vec<u8>, Source), ExecError> {
    let (major, minor) = nvrtc_version()?;
    let version = format!("nvrtc {major}.{minor}");
    let joined = options.join(" ");
    let key = fnv1a(&[version.as_bytes(), joined.as_bytes(), source.as_bytes()]);
    let path = crate::kernel_cache_dir().map(|d| d.join(format!("{key:016x}.cubin")));
    if let Some(p) = &path
        && let Ok(code) = std::fs::read(p)
        && !code.is_empty()
    {
        return Ok((code, Source::Cache(p.clone())));
    }
    let code = compile(what, source, options)?;
    if let Some(p) = &path {
        store(p, &code);
    }
    Ok((code, Source::Compiled))
}

/// Writes `code` to `path` through a file of its own beside it, so that a concurrent reader never sees
/// half of it; a failure is logged and otherwise ignored (the next start compiles again).
fn store(path: &std::path::Path, code: &[u8]) {
    let tmp = path.with_extension(format!("{}.tmp", std::process::id()));
    let written = path
        .parent()
        .map_or(Ok(()), std::fs::create_dir_all)
        .and_then(|()| std::fs::write(&tmp, code))
        .and_then(|()| std::fs::rename(&tmp, path));
    if let Err(e) = written {
        let _ = std::fs::remove_file(&tmp);
        tracing::debug!("kernel cache {}: not written ({e})", path.display());
    }
}

/// NVRTC's machine code for `source`.
fn compile(what: &str, source: &str, options: &[String]) -> Result<Vec<u8>, ExecError> {
    let fail = |e: String| device("NVRTC")(format!("{what}: {e}"));
    let src = CString::new(source).map_err(|_| fail("the source holds a NUL byte".into()))?;
    let prog = nvrtc::create_program(&src, None).map_err(|e| fail(format!("{e:?}")))?;
    // SAFETY: `prog` was created above from `src`, which outlives it, and is destroyed once, at the end;
    // the buffers handed to NVRTC are as large as it says.
    unsafe {
        let made = match nvrtc::compile_program(prog, options) {
            Err(e) => {
                let log = nvrtc::get_program_log(prog)
                    .map(|l| CStr::from_ptr(l.as_ptr()).to_string_lossy().into_owned())
                    .unwrap_or_default();
                Err(fail(format!("{e:?}: {log}")))
            }
            Ok(()) => {
                let mut size = 0usize;
                nvrtc_sys::nvrtcGetCUBINSize(prog, &mut size)
                    .result()
                    .and_then(|()| {
                        let mut code = vec![0u8; size];
                        nvrtc_sys::nvrtcGetCUBIN(prog, code.as_mut_ptr().cast())
                            .result()
                            .map(|()| code)
                    })
                    .map_err(|e| fail(format!("machine code: {e:?}")))
            }
        };
        let _ = nvrtc::destroy_program(prog);
        made
    }
}

#[cfg(test)]
mod tests {
    use super::fnv1a;

    #[test]
    fn the_cache_key_separates_its_parts_and_follows_every_byte() {
        // The published FNV-1a test vector ("a"), then the 0 byte that ends a part (xor with 0 is a no-op).
        let a = 0xaf63_dc4c_8601_ec8cu64;
        assert_eq!(fnv1a(&[b"a"]), a.wrapping_mul(0x0100_0000_01b3));
        assert_ne!(fnv1a(&[b"ab", b"c"]), fnv1a(&[b"a", b"bc"]));
        assert_ne!(fnv1a(&[b"x", b"kernel"]), fnv1a(&[b"x", b"kernel "]));
    }
}
