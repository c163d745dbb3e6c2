//! [`NamedMatmul`] for `Cuda` (burn-fusion over the cubecl backend): a custom operation in the fusion
//! stream that launches cubek's `specialized_tma_mma` (or cuBLAS, `cublas.rs`, with `train.kernels.matmul =
//! "cublas"`) on the two operands as they lie in memory, row- or column-major, and writes the result in the
//! format asked for (f32, or bf16 from bf16 operands), accumulating in f32.
//!
//! The fusion stream cannot fuse a custom operation, so element-wise work around a product (a bias, a
//! cast) runs as its own kernels instead of inside burn's fused matmul; the kernel's speed pays for that
//! many times over on the training step's shapes (`umgen-kernel-bench matmul`, `docs/decisions/006-products-on-cublas-in-bf16.md`).

use super::NamedMatmul;
use super::cublaslt::Epilogue;
use crate::format::{float, float_format};
use crate::kernels::{EpilogueKernel, Kernels};
use crate::side::{Handles, Inner, Primitive};
use burn::backend::Cuda;
use burn::cubecl::cuda::CudaRuntime;
use burn::tensor::ops::{FloatTensor, FloatTensorOps};
use burn::tensor::{DType, FloatDType, Shape};
use burn_cubecl::fusion::FusionCubeRuntime;
use burn_cubecl::kernel::into_contiguous;
use burn_cubecl::kernel::matmul::{MatmulStrategy, init_matmul_output, matmul};
use burn_fusion::stream::{Operation, OperationStreams};
use burn_ir::{CustomOpIr, OperationIr, OperationOutput, TensorIr};
use cubek::matmul::definition::{MatmulElems, MatmulGlobalElems};
use cubek::matmul::launch::Strategy;
use cubek::matmul::routines::BlueprintStrategy;
use cubek::std::InputBinding;
use std::sync::atomic::{AtomicUsize, Ordering};

/// Products that fell back: from cuBLAS to the named kernel, or from the named kernel to burn's default.
static FALLBACKS: AtomicUsize = AtomicUsize::new(0);

/// How many products fell back (cuBLAS to the named kernel, or it to burn's default) in this process; the
/// first is logged with its reason at `warn`, the rest at `debug`.
pub fn fallbacks() -> usize {
    FALLBACKS.load(Ordering::Relaxed)
}

impl NamedMatmul for Cuda {
    fn named_matmul(
        lhs: FloatTensor<Self>,
        rhs: FloatTensor<Self>,
        out: FloatDType,
        kernels: &Kernels,
    ) -> FloatTensor<Self> {
        let client = lhs.client.clone();
        let shape = Shape::new([lhs.shape[0], rhs.shape[1]]);
        let out = TensorIr::uninit(client.create_empty_handle(), shape, DType::from(out));
        let streams = OperationStreams::with_inputs([&lhs, &rhs]);
        let desc = CustomOpIr::new("umgen_named_matmul", &[lhs.into_ir(), rhs.into_ir()], &[out]);
        client
            .register(
                streams,
                OperationIr::Custom(desc.clone()),
                Product {
                    desc,
                    kernels: *kernels,
                },
            )
            .output()
    }

    fn named_matmul_epilogue(
        lhs: FloatTensor<Self>,
        rhs: FloatTensor<Self>,
        (bias, add): (Option<FloatTensor<Self>>, Option<FloatTensor<Self>>),
        out: FloatDType,
        kernels: &Kernels,
    ) -> FloatTensor<Self> {
        if kernels.matmul != super::MatmulKernel::Cublas || kernels.epilogue == EpilogueKernel::Apart {
            return super::epilogue_decomposed::<Self>(lhs, rhs, (bias, add), out, kernels);
        }
        let client = lhs.client.clone();
        let shape = Shape::new([lhs.shape[0], rhs.shape[1]]);
        let out = TensorIr::uninit(client.create_empty_handle(), shape, DType::from(out));
        let has = (bias.is_some(), add.is_some());
        let inputs: Vec<_> = [Some(lhs), Some(rhs), bias, add].into_iter().flatten().collect();
        let streams = OperationStreams::with_inputs(inputs.iter());
        let irs: Vec<TensorIr> = inputs.into_iter().map(|t| t.into_ir()).collect();
        let desc = CustomOpIr::new("umgen_named_matmul_epilogue", &irs, &[out]);
        client
            .register(
                streams,
                OperationIr::Custom(desc.clone()),
                WithEpilogue {
                    desc,
                    has,
                    kernels: *kernels,
                },
            )
            .output()
    }
}

/// [`NamedMatmul::named_matmul_epilogue`]'s operation as the fusion stream runs it.
#[derive(Debug)]
struct WithEpilogue {
    desc: CustomOpIr,
    /// Whether a bias and added rows follow the operands among the inputs.
    has: (bool, bool),
    kernels: Kernels,
}

impl Operation<FusionCubeRuntime<CudaRuntime>> for WithEpilogue {
    fn execute(&self, handles: &mut Handles) {
        let mut inputs = self
            .desc
            .inputs
            .iter()
            .map(|t| handles.get_float_tensor::<Inner>(t));
        let mut next = || {
            inputs
                .next()
                .unwrap_or_else(|| unreachable!("umgen_named_matmul_epilogue was described with its inputs"))
        };
        let (lhs, rhs) = (next(), next());
        let bias = self.has.0.then(&mut next);
        let add = self.has.1.then(&mut next);
        let [o] = &self.desc.outputs[..] else {
            unreachable!("umgen_named_matmul_epilogue was described with one output")
        };
        let y = run_epilogue(lhs, rhs, (bias, add), o.dtype, &self.kernels);
        handles.register_float_tensor::<Inner>(&o.id, y);
    }
}

/// `lhs · rhs + bias + add` in `dtype` on cuBLASLt, else (where it refuses, counted) the product and then
/// the additions as element-wise kernels.
fn run_epilogue(
    lhs: Primitive,
    rhs: Primitive,
    (bias, add): (Option<Primitive>, Option<Primitive>),
    dtype: DType,
    kernels: &Kernels,
) -> Primitive {
    let format = float_format(dtype);
    // In the result's format, as cuBLASLt reads them (a bf16 result's f32 bias rounded once).
    let cast = |t: Primitive| match t.dtype == dtype {
        true => t,
        false => Inner::float_cast(t, format),
    };
    let bias = bias.map(|b| into_contiguous(cast(b)));
    let add = add.map(cast);
    let out = init_matmul_output(&lhs, &rhs, dtype);
    let epilogue = Epilogue {
        bias: bias.as_ref(),
        add: add.as_ref(),
    };
    match crate::side::on_device_thread(&lhs, kernels.launch_thread, || {
        super::cublaslt::launch(&lhs, &rhs, &out, epilogue, kernels)
    }) {
        Ok(()) => return out,
        Err(why) => fell_back(
            "cuBLASLt",
            "the product and element-wise additions",
            &lhs,
            &rhs,
            &why,
        ),
    }
    let y = float::<Inner, 2>(run(lhs, rhs, DType::F32, kernels));
    super::added(y, (bias, add), format).into_primitive().tensor()
}

/// The operation as the fusion stream runs it.
#[derive(Debug)]
struct Product {
    desc: CustomOpIr,
    /// cuBLAS or the named kernel, the stream and the launching thread.
    kernels: Kernels,
}

impl Operation<FusionCubeRuntime<CudaRuntime>> for Product {
    fn execute(&self, handles: &mut Handles) {
        let ([l, r], [o]) = self.desc.as_fixed();
        let lhs = handles.get_float_tensor::<Inner>(l);
        let rhs = handles.get_float_tensor::<Inner>(r);
        handles.register_float_tensor::<Inner>(&o.id, run(lhs, rhs, o.dtype, &self.kernels));
    }
}

/// The kernel.
fn strategy() -> Strategy {
    Strategy::SpecializedTmaMma(BlueprintStrategy::Inferred(().into()))
}

/// Why the tensor-memory-accelerator kernel cannot read `t`, if it cannot: it needs a matrix whose rows or
/// columns are contiguous and whose other stride is a multiple of 16 bytes.
fn unfit(t: &Primitive) -> Option<String> {
    let (shape, strides) = (t.meta.shape(), t.meta.strides());
    if shape.len() != 2 || strides.len() != 2 {
        return Some(format!("rank {}", shape.len()));
    }
    let lead = match (strides[0], strides[1]) {
        (s, 1) => s,
        (1, s) => s,
        (a, b) => return Some(format!("strides [{a}, {b}]")),
    };
    if t.qparams.is_some() {
        return Some("quantized operand".into());
    }
    (!(lead * t.elem_size()).is_multiple_of(16))
        .then(|| format!("leading stride {lead} × {} bytes", t.elem_size()))
}

fn launch(lhs: &Primitive, rhs: &Primitive, out: &Primitive) -> Result<(), String> {
    if let Some(why) = unfit(lhs).or_else(|| unfit(rhs)) {
        return Err(why);
    }
    launch_kernel(&strategy(), lhs, rhs, out)
}

/// Launches cubek's matmul kernel `strategy` once on `lhs × rhs` into `out` (formats as the tensors have
/// them); a kernel that cannot take the shape or format says why. `umgen-kernel-bench matmul` times every
/// strategy through this.
pub fn launch_kernel(
    strategy: &Strategy,
    lhs: &Primitive,
    rhs: &Primitive,
    out: &Primitive,
) -> Result<(), String> {
    let mut elems = MatmulElems::from_globals(&MatmulGlobalElems {
        lhs: lhs.dtype.into(),
        rhs: rhs.dtype.into(),
        out: out.dtype.into(),
    });
    let l = InputBinding::new(lhs.clone().binding(), lhs.dtype.into());
    let r = InputBinding::new(rhs.clone().binding(), rhs.dtype.into());
    let client = lhs.client.clone();
    // Some kernels assert on shapes they cannot tile instead of returning an error.
    std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| {
        cubek::matmul::launch::launch_ref(strategy, &client, l, r, out.clone().binding(), &mut elems)
    }))
    .map_err(|_| "the kernel panicked".to_string())?
    .map_err(|e| format!("{e:?}"))
}

/// Counts and logs a product that `kernel` refused (the first at `warn`, the rest at `debug`).
fn fell_back(kernel: &str, instead: &str, lhs: &Primitive, rhs: &Primitive, why: &str) {
    let n = FALLBACKS.fetch_add(1, Ordering::Relaxed) + 1;
    let what = format!(
        "{:?} × {:?} ({:?}): {why}",
        lhs.meta.shape(),
        rhs.meta.shape(),
        lhs.dtype
    );
    if n == 1 {
        tracing::warn!("{kernel} refused {what}; {instead} runs it (counted in fallbacks)");
    } else {
        tracing::debug!("matmul fallback #{n} ({kernel}): {what}");
    }
}

/// `lhs · rhs` in `dtype` on cuBLAS when selected, else (or when it refuses) on the named kernel, else on
/// burn's default kernel.
fn run(lhs: Primitive, rhs: Primitive, dtype: DType, kernels: &Kernels) -> Primitive {
    let out = init_matmul_output(&lhs, &rhs, dtype);
    if kernels.matmul == super::MatmulKernel::Cublas {
        match crate::side::on_device_thread(&lhs, kernels.launch_thread, || {
            super::cublas::launch(&lhs, &rhs, &out, kernels)
        }) {
            Ok(()) => return out,
            Err(why) => fell_back("cuBLAS", "the named kernel", &lhs, &rhs, &why),
        }
    }
    match launch(&lhs, &rhs, &out) {
        Ok(()) => return out,
        Err(why) => fell_back(
            "the named matmul kernel",
            "burn's default kernel",
            &lhs,
            &rhs,
            &why,
        ),
    }
    match matmul(lhs.clone(), rhs.clone(), None, MatmulStrategy::default(), dtype) {
        Ok(out) => out,
        // burn's default kernel writes the operands' own format; cast after it.
        Err(_) => Inner::float_cast(Inner::float_matmul(lhs, rhs), float_format(dtype)),
    }
}
