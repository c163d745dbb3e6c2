//! The generation engine on the device a command names: CUDA graphs on a GPU (`CudaExec`), the host
//! executor on the CPU.

use crate::cli::EnginePrecisionArg;
use crate::device::Device;
use umgen::backbone::PlainBackbone;
use umgen::generate::engine::{Engine, EngineSettings, HostExec, Times};
use umgen::generate::{FrameControl, NextFrame};

/// The engine on one executor or the other.
pub enum AnyEngine {
    /// On the host.
    Host(Engine<HostExec>),
    /// On a GPU.
    #[cfg(feature = "cuda")]
    Cuda(Engine<umgen_cuda::gpu::CudaExec>),
}

impl AnyEngine {
    /// The engine for `model` on `device`, its weights in bf16 or f32 as `precision` says (the host
    /// executor computes in f32).
    pub fn new(
        device: Device,
        model: &PlainBackbone,
        settings: EngineSettings,
        precision: EnginePrecisionArg,
    ) -> anyhow::Result<Self> {
        match device {
            Device::Cpu => {
                if precision == EnginePrecisionArg::Bf16 {
                    tracing::warn!("--precision bf16: the engine on the CPU computes in f32");
                }
                Ok(Self::Host(Engine::new(HostExec::new(), model, settings)?))
            }
            #[cfg(feature = "cuda")]
            Device::Cuda(i) => {
                let bf16 = precision != EnginePrecisionArg::F32;
                let x = umgen_cuda::gpu::CudaExec::new(i, bf16)?;
                tracing::info!(
                    "generation engine on {} ({})",
                    x.name(),
                    if bf16 { "bf16 weights and products" } else { "f32" }
                );
                Ok(Self::Cuda(Engine::new(x, model, settings)?))
            }
            #[cfg(not(feature = "cuda"))]
            Device::Cuda(_) => anyhow::bail!("built without CUDA"),
        }
    }

    /// Waits for the device after each part of a frame and adds up their times.
    pub fn timed(self, on: bool) -> Self {
        match self {
            Self::Host(e) => Self::Host(e.timed(on)),
            #[cfg(feature = "cuda")]
            Self::Cuda(e) => Self::Cuda(e.timed(on)),
        }
    }

    /// Times the window pass's operations by kind from now on.
    pub fn profiled(self, on: bool) -> Self {
        match self {
            Self::Host(e) => Self::Host(e.profiled(on)),
            #[cfg(feature = "cuda")]
            Self::Cuda(e) => Self::Cuda(e.profiled(on)),
        }
    }

    /// The window pass's operations' seconds and counts by kind.
    pub fn window_profile(&self) -> Vec<(String, f64, u64)> {
        match self {
            Self::Host(e) => e.window_profile(),
            #[cfg(feature = "cuda")]
            Self::Cuda(e) => e.window_profile(),
        }
    }

    /// Microseconds per run of each operation of a decoding step.
    pub fn profile_step(&mut self, reps: usize) -> anyhow::Result<Vec<(String, f64, bool)>> {
        Ok(match self {
            Self::Host(e) => e.profile_step(reps)?,
            #[cfg(feature = "cuda")]
            Self::Cuda(e) => e.profile_step(reps)?,
        })
    }

    /// The parts' times so far.
    pub fn times(&self) -> Times {
        match self {
            Self::Host(e) => e.times(),
            #[cfg(feature = "cuda")]
            Self::Cuda(e) => e.times(),
        }
    }

    /// Bytes its buffers hold (on the device, for a GPU).
    pub fn bytes(&self) -> usize {
        match self {
            Self::Host(e) => e.bytes(),
            #[cfg(feature = "cuda")]
            Self::Cuda(e) => e.bytes(),
        }
    }

    /// Bytes of the device's memory in use (every context on it: the CUDA context, kernels, cuBLAS and
    /// the buffers); `None` on the CPU.
    pub fn device_memory(&self) -> Option<usize> {
        match self {
            Self::Host(_) => None,
            #[cfg(feature = "cuda")]
            Self::Cuda(e) => e.executor().device_memory().ok(),
        }
    }
}

impl NextFrame for AnyEngine {
    fn next_frame(
        &mut self,
        history: &[Vec<Vec<u32>>],
        control: &FrameControl,
    ) -> umgen::generate::Result<Vec<Vec<u32>>> {
        match self {
            Self::Host(e) => e.next_frame(history, control),
            #[cfg(feature = "cuda")]
            Self::Cuda(e) => e.next_frame(history, control),
        }
    }

    fn new_agents(&self) -> (u64, u64) {
        match self {
            Self::Host(e) => e.new_agents(),
            #[cfg(feature = "cuda")]
            Self::Cuda(e) => e.new_agents(),
        }
    }
}
