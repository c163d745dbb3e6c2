//! cuBLAS for the named products (`train.kernels.matmul = "cublas"`): `cublasGemmEx` on the operands as they lie in
//! burn's memory, f32 or bf16 operands (f32 through TF32 tensor cores, as the cubek kernel does), an f32
//! result (or one in the operands' own 16-bit format), f32 accumulation.
//!
//! With `train.kernels.stream = "cubecl"` (the default) each product is queued on cubecl's own stream for
//! the caller (`cubecl_cuda::last_stream`, right after the operands' pointers were fetched on cubecl's
//! device thread), in order with everything cubecl queues before and after it. With `"side"` the products
//! run on a [`Side`] stream, ordered with cubecl's stream on the device (`side.rs`): four more launches a
//! product (a signal, a wait and their answers), which the default saves.
#![allow(unsafe_code)]

#[cfg(feature = "patched-cubecl")]
use crate::kernels::{KernelStream, LaunchThread};
use crate::kernels::{Kernels, SideFamily};
use crate::side::Primitive;
use crate::side::{Cache, Side, pointer, with_cached};
use burn::tensor::DType;
use cudarc::cublas::{result as blas, sys};
use std::cell::RefCell;
use std::ffi::c_void;

/// A cuBLAS handle on a side stream, for one device and the calling thread. The handle is never destroyed:
/// it lives as long as its thread (training threads live as long as the process), and calling into cuBLAS
/// from a thread-local destructor at process exit, while CUDA may be tearing down, is a risk this does not
/// take; the driver reclaims it with the process.
struct Blas {
    /// The side stream, made on first use (`train.kernels.stream = "side"`, or launches from the caller's
    /// thread).
    side: Option<Side>,
    handle: sys::cublasHandle_t,
    /// The stream `handle` was last set to (null before the first product).
    stream: sys::cudaStream_t,
}

thread_local! {
    /// This thread's handles by device and cubecl stream (the products run on cubecl's device thread, for
    /// every caller: `side::on_device_thread`); every product falls back without retrying where a device
    /// has none.
    static HANDLES: Cache<Blas> = const { RefCell::new(Vec::new()) };
}

impl Blas {
    fn new() -> Result<Self, String> {
        // SAFETY: only asks whether the library could be loaded.
        if !unsafe { sys::is_culib_present() } {
            return Err("libcublas (CUDA 13: libcublas.so.13) is not on the library path".into());
        }
        let handle = blas::create_handle().map_err(|e| format!("cublasCreate: {e:?}"))?;
        Ok(Self {
            side: None,
            handle,
            stream: std::ptr::null_mut(),
        })
    }

    /// Points the handle at `stream` where it points elsewhere (products on one stream set it once).
    fn use_stream(&mut self, stream: sys::cudaStream_t) -> Result<(), String> {
        if stream != self.stream {
            // SAFETY: a live handle and a live stream of its context (cubecl never destroys its streams; the
            // side stream lives as long as this handle).
            unsafe { blas::set_stream(self.handle, stream) }
                .map_err(|e| format!("cublasSetStream: {e:?}"))?;
            self.stream = stream;
        }
        Ok(())
    }

    /// Runs `gemm` between cubecl's queued work and what cubecl queues next: on cubecl's stream for the
    /// caller where this runs on cubecl's device thread right after the operands' pointers were fetched
    /// (the stream cubecl resolved for them), else on the side stream ordered with it.
    fn ordered(
        &mut self,
        like: &Primitive,
        kernels: &Kernels,
        gemm: impl FnOnce(sys::cublasHandle_t, sys::cudaStream_t) -> Result<(), String>,
    ) -> Result<(), String> {
        let handle = self.handle;
        // `last_stream` is an API of the vendored cubecl-cuda (vendor/README.md); built against an
        // unpatched one, cuBLAS runs on the side stream.
        #[cfg(feature = "patched-cubecl")]
        if kernels.stream == KernelStream::Cubecl && kernels.launch_thread == LaunchThread::Device {
            // The stream cubecl resolved for the caller's last command on this thread.
            let stream = burn::cubecl::cuda::last_stream();
            if stream.is_null() {
                return Err("no cubecl stream resolved on this thread".into());
            }
            self.use_stream(stream as sys::cudaStream_t)?;
            return gemm(handle, stream as sys::cudaStream_t);
        }
        if self.side.is_none() {
            self.side = Some(Side::new(like)?);
        }
        let stream = self.side.as_ref().ok_or("no side stream")?.stream().cu_stream();
        self.use_stream(stream as sys::cudaStream_t)?;
        let side = self.side.as_mut().ok_or("no side stream")?;
        side.ordered((SideFamily::Cublas, kernels.side_sync), |_| {
            gemm(handle, stream as sys::cudaStream_t)
        })
    }
}

/// How one operand enters `cublasGemmEx`: its pointer, whether cuBLAS transposes it, its leading dimension.
pub(super) struct Operand {
    pub ptr: u64,
    pub op: sys::cublasOperation_t,
    pub ld: i32,
}

/// The product's element types: cuBLAS's operand type and compute type for `dtype`.
fn types(dtype: DType) -> Result<(sys::cudaDataType, sys::cublasComputeType_t), String> {
    use sys::cublasComputeType_t::{CUBLAS_COMPUTE_32F, CUBLAS_COMPUTE_32F_FAST_TF32};
    use sys::cudaDataType::{CUDA_R_16BF, CUDA_R_16F, CUDA_R_32F};
    match dtype {
        DType::F32 => Ok((CUDA_R_32F, CUBLAS_COMPUTE_32F_FAST_TF32)),
        DType::BF16 => Ok((CUDA_R_16BF, CUBLAS_COMPUTE_32F)),
        DType::F16 => Ok((CUDA_R_16F, CUBLAS_COMPUTE_32F)),
        other => Err(format!("{other:?} operands")),
    }
}

/// The layout of a `[rows, cols]` row-major operand in cuBLAS's column-major terms, where the product needs
/// it as its `cols × rows` transpose: a row-major matrix (strides `[ld, 1]`) is that transpose as stored, a
/// column-major one (strides `[1, ld]`) is transposed by cuBLAS. `None` when it is neither or cuBLAS would
/// reject the leading dimension.
pub(super) fn layout(shape: [usize; 2], strides: [usize; 2]) -> Option<(sys::cublasOperation_t, usize)> {
    use sys::cublasOperation_t::{CUBLAS_OP_N, CUBLAS_OP_T};
    let [rows, cols] = shape;
    // A dimension of 1 leaves its stride free; give it the value that makes the layout valid.
    let row_major = strides[1] == 1 || cols == 1;
    let col_major = strides[0] == 1 || rows == 1;
    if row_major && (strides[0] >= cols.max(1) || rows == 1) {
        Some((CUBLAS_OP_N, strides[0].max(cols).max(1)))
    } else if col_major && (strides[1] >= rows.max(1) || cols == 1) {
        Some((CUBLAS_OP_T, strides[1].max(rows).max(1)))
    } else {
        None
    }
}

pub(super) fn int(what: &str, v: usize) -> Result<i32, String> {
    i32::try_from(v).map_err(|_| format!("{what} {v} exceeds cuBLAS's 32-bit sizes"))
}

/// `out = lhs · rhs` on cuBLAS: `lhs [m, k]`, `rhs [k, n]` of one float format, row- or column-major, and
/// `out [m, n]` row-major, f32 or the operands' own format, ordered with cubecl's stream on the device (module docs). An operand cuBLAS
/// cannot take, or a device without cuBLAS, says why (the caller falls back, after cubecl's stream has
/// passed the failed product).
pub(super) fn launch(
    lhs: &Primitive,
    rhs: &Primitive,
    out: &Primitive,
    kernels: &Kernels,
) -> Result<(), String> {
    if lhs.dtype != rhs.dtype {
        return Err(format!("mixed operands {:?} × {:?}", lhs.dtype, rhs.dtype));
    }
    if lhs.qparams.is_some() || rhs.qparams.is_some() {
        return Err("quantized operand".into());
    }
    let (data, compute) = types(lhs.dtype)?;
    let dims = |t: &Primitive| -> Result<([usize; 2], [usize; 2]), String> {
        match (&t.meta.shape()[..], &t.meta.strides()[..]) {
            ([r, c], [s0, s1]) => Ok(([*r, *c], [*s0, *s1])),
            (s, _) => Err(format!("rank {}", s.len())),
        }
    };
    let ((ls, lst), (rs, rst), (os, ost)) = (dims(lhs)?, dims(rhs)?, dims(out)?);
    let (m, k, n) = (ls[0], ls[1], rs[1]);
    let written = match out.dtype {
        DType::F32 => sys::cudaDataType::CUDA_R_32F,
        d if d == lhs.dtype => data,
        _ => return Err(format!("{:?} result of {:?} operands", out.dtype, lhs.dtype)),
    };
    if rs[0] != k || os != [m, n] {
        return Err(format!("shapes {ls:?} × {rs:?} into {os:?} {:?}", out.dtype));
    }
    // burn pads the rows of some outputs (a head of 1,028 ids gets a longer row stride): any row-major
    // result will do, as cuBLAS's column-major transpose with that leading dimension.
    let ldc = match layout(os, ost) {
        Some((sys::cublasOperation_t::CUBLAS_OP_N, ld)) => ld,
        _ => return Err(format!("result strides {ost:?}")),
    };
    if m == 0 || n == 0 || k == 0 {
        return Err("an empty dimension".into());
    }
    let (a_op, lda) = layout(rs, rst).ok_or_else(|| format!("rhs strides {rst:?}"))?;
    let (b_op, ldb) = layout(ls, lst).ok_or_else(|| format!("lhs strides {lst:?}"))?;
    let (mi, ni, ki) = (int("n", n)?, int("m", m)?, int("k", k)?);
    let (lda, ldb, ldc) = (int("lda", lda)?, int("ldb", ldb)?, int("ldc", ldc)?);

    // Row-major out = lhs · rhs is column-major outᵀ = rhsᵀ · lhsᵀ: cuBLAS's A is rhs, its B is lhs.
    let (a, _keep_a) = pointer(rhs)?;
    let (b, _keep_b) = pointer(lhs)?;
    let (c, _keep_c) = pointer(out)?;
    let a = Operand {
        ptr: a,
        op: a_op,
        ld: lda,
    };
    let b = Operand {
        ptr: b,
        op: b_op,
        ld: ldb,
    };
    let gemm = |handle, _| {
        let (one, zero) = (1.0f32, 0.0f32);
        // SAFETY: the three pointers are live burn buffers holding the shapes and strides checked above,
        // and cubecl's stream waits for the product before anything queued later can free or reuse them;
        // the scalars are f32 as the compute types ask.
        unsafe {
            blas::gemm_ex(
                handle,
                a.op,
                b.op,
                mi,
                ni,
                ki,
                (&one as *const f32).cast::<c_void>(),
                a.ptr as *const c_void,
                data,
                a.ld,
                b.ptr as *const c_void,
                data,
                b.ld,
                (&zero as *const f32).cast::<c_void>(),
                c as *mut c_void,
                written,
                ldc,
                compute,
                sys::cublasGemmAlgo_t::CUBLAS_GEMM_DEFAULT,
            )
        }
        .map_err(|e| format!("cublasGemmEx: {e:?}"))
    };
    with_cached(&HANDLES, lhs, "cuBLAS", Blas::new, |blas| {
        blas.ordered(lhs, kernels, gemm)
    })
}

/// Runs `work` with the stream a product runs on, ordered with cubecl's (module docs): cuBLASLt's products
/// (`cublaslt.rs`) go where `cublasGemmEx`'s go.
pub(super) fn on_stream(
    like: &Primitive,
    kernels: &Kernels,
    work: impl FnOnce(sys::cudaStream_t) -> Result<(), String>,
) -> Result<(), String> {
    with_cached(&HANDLES, like, "cuBLAS", Blas::new, |blas| {
        blas.ordered(like, kernels, |_, stream| work(stream))
    })
}

#[cfg(test)]
mod tests {
    use super::layout;
    use cudarc::cublas::sys::cublasOperation_t::{CUBLAS_OP_N, CUBLAS_OP_T};

    #[test]
    fn layouts_of_row_and_column_major_operands_and_their_refusals() {
        // Row-major [3, 4]: stored as cuBLAS's 4 × 3 column-major, the transpose the product needs.
        assert_eq!(layout([3, 4], [4, 1]), Some((CUBLAS_OP_N, 4)));
        // Padded rows keep their stride.
        assert_eq!(layout([3, 4], [8, 1]), Some((CUBLAS_OP_N, 8)));
        // A transposed view [3, 4] of a row-major [4, 3]: cuBLAS transposes it.
        assert_eq!(layout([3, 4], [1, 3]), Some((CUBLAS_OP_T, 3)));
        // One row: any row stride will do.
        assert_eq!(layout([1, 4], [0, 1]), Some((CUBLAS_OP_N, 4)));
        // Neither layout, or rows that overlap.
        assert_eq!(layout([3, 4], [8, 2]), None);
        assert_eq!(layout([3, 4], [2, 1]), None);
    }
}
