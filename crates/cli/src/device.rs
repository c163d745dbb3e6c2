//! `--device cpu|cuda:N`: which burn backend runs a command.

use umgen_tokenizer_vq::CodecLoader;

/// Where tensors live.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Device {
    /// burn's Flex CPU backend.
    Cpu,
    /// A CUDA GPU (builds with the `cuda` feature).
    Cuda(usize),
}

impl Device {
    /// Parses `cpu`, `cuda` or `cuda:N`.
    pub fn parse(s: &str) -> anyhow::Result<Self> {
        let d = match s {
            "cpu" => Device::Cpu,
            "cuda" => Device::Cuda(0),
            _ => match s.strip_prefix("cuda:").and_then(|n| n.parse().ok()) {
                Some(n) => Device::Cuda(n),
                None => anyhow::bail!("device `{s}`: expected cpu, cuda or cuda:N"),
            },
        };
        if matches!(d, Device::Cuda(_)) && !cfg!(feature = "cuda") {
            anyhow::bail!("device `{s}`: this umgen was built without CUDA; rebuild with `--features cuda`");
        }
        Ok(d)
    }

    /// A loader putting VQ tokenizers on this device.
    pub fn codec_loader(self) -> CodecLoader {
        match self {
            Device::Cpu => umgen_tokenizer_vq::cpu_loader(),
            #[cfg(feature = "cuda")]
            Device::Cuda(i) => std::sync::Arc::new(move |dir: &std::path::Path| {
                let dev = burn::backend::cuda::CudaDevice::new(i);
                let codec = umgen_tokenizer_vq::CodecOn::<burn::backend::Cuda>::load(dir, &dev)?;
                Ok(std::sync::Arc::new(codec) as std::sync::Arc<dyn umgen_tokenizer_vq::Codec>)
            }),
            // `parse` refuses CUDA devices in builds without CUDA.
            #[cfg(not(feature = "cuda"))]
            Device::Cuda(_) => umgen_tokenizer_vq::cpu_loader(),
        }
    }
}

/// Runs `$body` with `$B` bound to `$cpu` or `$cuda` (as `$device` says) and `$dev` to its burn device;
/// `with_autodiff!` and `with_inference!` name the backends.
#[macro_export]
macro_rules! with_backend {
    ($device:expr, $cpu:ty, $cuda:ty, |$B:ident, $dev:ident| $body:block) => {
        match $device {
            $crate::device::Device::Cpu => {
                type $B = $cpu;
                let $dev: burn::backend::flex::FlexDevice = Default::default();
                $body
            }
            #[cfg(feature = "cuda")]
            $crate::device::Device::Cuda(i) => {
                type $B = $cuda;
                let $dev = burn::backend::cuda::CudaDevice::new(i);
                $body
            }
            #[cfg(not(feature = "cuda"))]
            $crate::device::Device::Cuda(_) => anyhow::bail!("built without CUDA"),
        }
    };
}

/// Runs `$body` with `$B` bound to the autodiff backend of `$device` and `$dev` to its burn device.
#[macro_export]
macro_rules! with_autodiff {
    ($device:expr, |$B:ident, $dev:ident| $body:block) => {
        $crate::with_backend!(
            $device,
            burn::backend::Autodiff<burn::backend::Flex>,
            burn::backend::Autodiff<burn::backend::Cuda>,
            |$B, $dev| $body
        )
    };
}

/// Runs `$body` with `$B` bound to the inference backend of `$device` and `$dev` to its burn device. On CUDA
/// that is the plain cubecl backend, without burn's fusion: fusion keeps an execution plan per sequence of
/// operations it has seen, with the operations that followed each one as triggers, and token-by-token decoding
/// (a slice at a new position every step) grows those lists without end, so its host thread spent minutes
/// matching plans while the GPU sat idle (a `small` frame did not finish in minutes). Plain kernels launch at once.
#[macro_export]
macro_rules! with_inference {
    ($device:expr, |$B:ident, $dev:ident| $body:block) => {
        $crate::with_backend!(
            $device,
            burn::backend::Flex,
            burn_cubecl::CubeBackend<burn::cubecl::cuda::CudaRuntime, f32, i32, u8>,
            |$B, $dev| $body
        )
    };
}

/// A reading of the device's memory pool, in bytes (zeros on the CPU or when unknown).
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct Memory {
    /// Held by live tensors (with their alignment padding).
    pub in_use: u64,
    /// Reserved from the driver by the pool; it only grows, so it is the peak of the pool.
    pub reserved: u64,
}

/// The device's memory pool now.
pub fn memory(device: Device) -> Memory {
    match device {
        Device::Cpu => Memory::default(),
        #[cfg(feature = "cuda")]
        Device::Cuda(i) => {
            use burn::cubecl::Runtime;
            let dev = burn::backend::cuda::CudaDevice::new(i);
            burn::cubecl::cuda::CudaRuntime::client(&dev)
                .memory_usage()
                .map_or(Memory::default(), |m| Memory {
                    in_use: m.bytes_in_use + m.bytes_padding,
                    reserved: m.bytes_reserved,
                })
        }
        #[cfg(not(feature = "cuda"))]
        Device::Cuda(_) => Memory::default(),
    }
}

/// What cubecl's device thread has done for the host so far, each as (count, seconds): the custom
/// operations run on it and the calling threads' time in them (each waits for the thread's backlog), then
/// the kernels it launched and its time in cubecl-cuda's launch path (the vendored cubecl-cuda's count).
/// Zeros on the CPU or when the thread cannot be reached; reading the launches waits for that thread to
/// run what is queued before.
pub fn device_thread(device: Device) -> [(u64, f64); 2] {
    match device {
        Device::Cpu => [(0, 0.0); 2],
        #[cfg(feature = "cuda")]
        Device::Cuda(i) => {
            use burn::cubecl::Runtime;
            let dev = burn::backend::cuda::CudaDevice::new(i);
            // `launches` is an API of the vendored cubecl-cuda (vendor/README.md).
            #[cfg(feature = "patched-cubecl")]
            let launches = burn::cubecl::cuda::CudaRuntime::client(&dev)
                .exclusive(burn::cubecl::cuda::launches)
                .unwrap_or((0, 0.0));
            #[cfg(not(feature = "patched-cubecl"))]
            let launches = {
                let _ = burn::cubecl::cuda::CudaRuntime::client(&dev);
                (0, 0.0)
            };
            [umgen::ops::device_thread_calls(), launches]
        }
        #[cfg(not(feature = "cuda"))]
        Device::Cuda(_) => [(0, 0.0); 2],
    }
}

/// The peak of the device memory in use (live tensors with their padding, bytes) at the allocations made
/// since the last call, then measures again from 0 if `measure`, else stops (the vendored cubecl-cuda's
/// `peak_in_use`; vendor/README.md). Work queued but not yet run by cubecl's device thread is not counted:
/// sync the backend first. 0 on the CPU, when it was not measuring, or without the vendored cubecl.
pub fn peak_in_use(device: Device, measure: bool) -> u64 {
    match device {
        Device::Cpu => 0,
        #[cfg(all(feature = "cuda", feature = "patched-cubecl"))]
        Device::Cuda(i) => {
            use burn::cubecl::Runtime;
            let dev = burn::backend::cuda::CudaDevice::new(i);
            burn::cubecl::cuda::CudaRuntime::client(&dev)
                .exclusive(move || burn::cubecl::cuda::peak_in_use(measure))
                .unwrap_or(0)
        }
        #[cfg(not(all(feature = "cuda", feature = "patched-cubecl")))]
        Device::Cuda(_) => {
            let _ = measure;
            0
        }
    }
}

/// Bytes the device's memory pool holds now (0 on the CPU or when unknown).
pub fn memory_in_use(device: Device) -> u64 {
    memory(device).reserved
}

/// Keeps compiled CUDA kernels between processes. cubecl compiles every kernel with NVRTC at run time and,
/// unless a config names a cache, forgets them when the process ends, so every run and every rank of a
/// data-parallel run paid minutes of compilation again. A `cubecl.toml` (or a `burn.toml` with a `cubecl`
/// section) found from the working directory up still decides; without one that sets a compilation cache,
/// [`umgen_cuda::kernel_cache_dir`] is used. `CUBECL_*` variables apply on top, as they do for cubecl's own loading.
/// Call before any CUDA work; returns the cache directory chosen here, if any.
#[cfg(feature = "cuda")]
pub fn init_kernel_cache() -> Option<std::path::PathBuf> {
    use burn::cubecl::config::cache::CacheConfig;
    use burn::cubecl::config::{CubeClRuntimeConfig, RuntimeConfig};
    let mut cfg = CubeClRuntimeConfig::from_current_dir();
    let chosen = match cfg.compilation.cache {
        Some(_) => None,
        None => umgen_cuda::kernel_cache_dir(),
    };
    if let Some(dir) = &chosen {
        cfg.compilation.cache = Some(CacheConfig::File(dir.clone()));
    }
    CubeClRuntimeConfig::set(cfg.override_from_env());
    chosen
}
