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

/// Runs `$body` with `$B` bound to the autodiff backend of `$device` and `$dev` to its burn device.
#[macro_export]
macro_rules! with_autodiff {
    ($device:expr, |$B:ident, $dev:ident| $body:block) => {
        match $device {
            $crate::device::Device::Cpu => {
                type $B = burn::backend::Autodiff<burn::backend::Flex>;
                let $dev: burn::backend::flex::FlexDevice = Default::default();
                $body
            }
            #[cfg(feature = "cuda")]
            $crate::device::Device::Cuda(i) => {
                type $B = burn::backend::Autodiff<burn::backend::Cuda>;
                let $dev = burn::backend::cuda::CudaDevice::new(i);
                $body
            }
            #[cfg(not(feature = "cuda"))]
            $crate::device::Device::Cuda(_) => anyhow::bail!("built without CUDA"),
        }
    };
}

/// Bytes the device's memory pool holds now (0 on the CPU or when unknown).
pub fn memory_in_use(device: Device) -> u64 {
    match device {
        Device::Cpu => 0,
        #[cfg(feature = "cuda")]
        Device::Cuda(i) => {
            use burn::cubecl::Runtime;
            let dev = burn::backend::cuda::CudaDevice::new(i);
            burn::cubecl::cuda::CudaRuntime::client(&dev)
                .memory_usage()
                .map_or(0, |m| m.bytes_reserved)
        }
        #[cfg(not(feature = "cuda"))]
        Device::Cuda(_) => 0,
    }
}
