//! cuBLASLt for the products with an epilogue (`train.kernels.matmul = "cublas"`): `out = lhs · rhs + bias +
//! add`, the bias `[n]` added to every row and `add` `[m, n]` (a residual stream, or another product's
//! result) summed by the product's own epilogue as it writes `out`. With `cublasGemmEx` each of them is an
//! element-wise pass over the result: about 0.1 ms a pass over a `[70,368, 384]` f32 activation of `small`
//! and 0.13 ms over `paper`'s `[43,980, 768]`, several per layer. PyTorch's compiled step adds its biases
//! the same way (`…_bias_…` kernels).
//!
//! Each shape's plan (descriptors and the algorithm cuBLASLt's heuristic picks for it, for the pointers'
//! alignments) is made once and kept with the handle; a call sets the bias pointer and launches. The
//! operands' layouts are `cublas.rs`'s; the product runs on the stream it says.
#![allow(unsafe_code)]

use super::cublas::{Operand, int, layout, on_stream};
use crate::kernels::Kernels;
use crate::side::{Cache, Primitive, pointer, with_cached};
use burn::tensor::DType;
use cudarc::cublaslt::{result as lt, sys};
use std::cell::RefCell;
use std::ffi::c_void;

/// The workspace each handle offers the algorithms that split a product's inner dimension.
const WORKSPACE: usize = 32 << 20;

/// What the epilogue adds to `lhs · rhs`: a bias `[n]` in the result's format, and `[m, n]` rows in it.
#[derive(Debug, Clone, Copy)]
pub(super) struct Epilogue<'a> {
    pub bias: Option<&'a Primitive>,
    pub add: Option<&'a Primitive>,
}

/// A cuBLASLt handle, its workspace and the plans made so far, for one device and cubecl stream. Like the
/// cuBLAS handle (`cublas.rs`), it lives as long as its thread and is reclaimed with the process.
struct Lt {
    handle: sys::cublasLtHandle_t,
    workspace: u64,
    plans: Vec<(Key, Plan)>,
}

thread_local! {
    static HANDLES: Cache<Lt> = const { RefCell::new(Vec::new()) };
}

/// Everything a plan depends on, in cuBLAS's column-major terms (`m` the result's columns, `n` its rows).
#[derive(Debug, Clone, Copy, PartialEq)]
struct Key {
    mnk: [u64; 3],
    ops: [i32; 2],
    /// Leading dimensions of A, B, C (`add`) and D (the result).
    lds: [i64; 4],
    data: sys::cudaDataType,
    out: sys::cudaDataType,
    compute: sys::cublasComputeType_t,
    bias: bool,
    /// The largest power of two (up to 256) dividing each of A's, B's, C's and D's addresses.
    align: [u32; 4],
}

/// A product's descriptors and algorithm.
struct Plan {
    desc: sys::cublasLtMatmulDesc_t,
    /// A, B, C and D.
    layouts: Vec<sys::cublasLtMatrixLayout_t>,
    algo: Option<sys::cublasLtMatmulAlgo_t>,
}

impl Drop for Plan {
    fn drop(&mut self) {
        // SAFETY: each descriptor was created by this plan and is destroyed once, here.
        unsafe {
            for l in self.layouts.drain(..) {
                let _ = lt::destroy_matrix_layout(l);
            }
            let _ = lt::destroy_matmul_desc(self.desc);
        }
    }
}

fn err(what: &str) -> impl Fn(cudarc::cublaslt::result::CublasError) -> String + '_ {
    move |e| format!("{what}: {e:?}")
}

/// Sets a descriptor attribute to `value`.
fn set<T>(
    desc: sys::cublasLtMatmulDesc_t,
    attr: sys::cublasLtMatmulDescAttributes_t,
    value: &T,
) -> Result<(), String> {
    // SAFETY: a live descriptor; `value` is the attribute's type and size as cuBLASLt documents it.
    unsafe { lt::set_matmul_desc_attribute(desc, attr, (value as *const T).cast(), size_of::<T>()) }
        .map_err(err("cublasLtMatmulDescSetAttribute"))
}

impl Plan {
    fn new(handle: sys::cublasLtHandle_t, key: &Key) -> Result<Self, String> {
        use sys::cublasLtMatmulDescAttributes_t as A;
        use sys::cublasLtMatmulPreferenceAttributes_t as P;
        let desc = lt::create_matmul_desc(key.compute, sys::cudaDataType::CUDA_R_32F)
            .map_err(err("cublasLtMatmulDescCreate"))?;
        let mut plan = Self {
            desc,
            layouts: Vec::with_capacity(4),
            algo: None,
        };
        set(desc, A::CUBLASLT_MATMUL_DESC_TRANSA, &key.ops[0])?;
        set(desc, A::CUBLASLT_MATMUL_DESC_TRANSB, &key.ops[1])?;
        let epilogue = if key.bias {
            sys::cublasLtEpilogue_t::CUBLASLT_EPILOGUE_BIAS
        } else {
            sys::cublasLtEpilogue_t::CUBLASLT_EPILOGUE_DEFAULT
        };
        set(desc, A::CUBLASLT_MATMUL_DESC_EPILOGUE, &epilogue)?;
        let [m, n, k] = key.mnk;
        // A stored as it is: m × k untransposed, k × m where cuBLAS transposes it; B likewise.
        let transposed = |op: i32, r: u64, c: u64| if op == 0 { (r, c) } else { (c, r) };
        let shapes = [
            (key.data, transposed(key.ops[0], m, k)),
            (key.data, transposed(key.ops[1], k, n)),
            (key.out, (m, n)),
            (key.out, (m, n)),
        ];
        for ((ty, (r, c)), ld) in shapes.into_iter().zip(key.lds) {
            let l = lt::create_matrix_layout(ty, r, c, ld).map_err(err("cublasLtMatrixLayoutCreate"))?;
            plan.layouts.push(l);
        }
        let pref = lt::create_matmul_pref().map_err(err("cublasLtMatmulPreferenceCreate"))?;
        let found = (|| {
            let prefs = [
                (P::CUBLASLT_MATMUL_PREF_MIN_ALIGNMENT_A_BYTES, key.align[0]),
                (P::CUBLASLT_MATMUL_PREF_MIN_ALIGNMENT_B_BYTES, key.align[1]),
                (P::CUBLASLT_MATMUL_PREF_MIN_ALIGNMENT_C_BYTES, key.align[2]),
                (P::CUBLASLT_MATMUL_PREF_MIN_ALIGNMENT_D_BYTES, key.align[3]),
            ];
            let bytes = WORKSPACE as u64;
            // SAFETY: a live preference; each value is the attribute's documented type (u64, u32).
            unsafe {
                lt::set_matmul_pref_attribute(
                    pref,
                    P::CUBLASLT_MATMUL_PREF_MAX_WORKSPACE_BYTES,
                    (&bytes as *const u64).cast(),
                    size_of::<u64>(),
                )
                .map_err(err("cublasLtMatmulPreferenceSetAttribute"))?;
                for (attr, v) in prefs {
                    lt::set_matmul_pref_attribute(pref, attr, (&v as *const u32).cast(), size_of::<u32>())
                        .map_err(err("cublasLtMatmulPreferenceSetAttribute"))?;
                }
                let l = &plan.layouts;
                lt::get_matmul_algo_heuristic(handle, desc, l[0], l[1], l[2], l[3], pref)
                    .map_err(err("cublasLtMatmulAlgoGetHeuristic"))
            }
        })();
        // SAFETY: created above, destroyed once.
        let _ = unsafe { lt::destroy_matmul_pref(pref) };
        plan.algo = Some(found?.algo);
        Ok(plan)
    }
}

impl Lt {
    fn new() -> Result<Self, String> {
        // SAFETY: only asks whether the library could be loaded.
        if !unsafe { sys::is_culib_present() } {
            return Err("libcublasLt (CUDA 13: libcublasLt.so.13) is not on the library path".into());
        }
        if !matches!(cudarc::driver::result::ctx::get_current(), Ok(Some(_))) {
            return Err("no current CUDA context for the cuBLASLt workspace".into());
        }
        let handle = lt::create_handle().map_err(err("cublasLtCreate"))?;
        // SAFETY: an allocation in the current context (checked above), kept for the handle's life.
        let workspace = unsafe { cudarc::driver::result::malloc_sync(WORKSPACE) }
            .map_err(|e| format!("cuMemAlloc of the cuBLASLt workspace: {e:?}"))?;
        Ok(Self {
            handle,
            workspace,
            plans: Vec::new(),
        })
    }

    fn plan(&mut self, key: Key) -> Result<&Plan, String> {
        let at = match self.plans.iter().position(|(k, _)| *k == key) {
            Some(i) => i,
            None => {
                let plan = Plan::new(self.handle, &key)?;
                self.plans.push((key, plan));
                self.plans.len() - 1
            }
        };
        Ok(&self.plans[at].1)
    }
}

/// The largest power of two, up to 256, that divides `ptr`.
fn alignment(ptr: u64) -> u32 {
    1 << ptr.trailing_zeros().min(8)
}

/// cuBLASLt's element and compute types for `dtype`.
fn types(dtype: DType) -> Result<(sys::cudaDataType, sys::cublasComputeType_t), String> {
    use sys::cublasComputeType_t::{CUBLAS_COMPUTE_32F, CUBLAS_COMPUTE_32F_FAST_TF32};
    use sys::cudaDataType::{CUDA_R_16BF, CUDA_R_32F};
    match dtype {
        DType::F32 => Ok((CUDA_R_32F, CUBLAS_COMPUTE_32F_FAST_TF32)),
        DType::BF16 => Ok((CUDA_R_16BF, CUBLAS_COMPUTE_32F)),
        other => Err(format!("{other:?} operands")),
    }
}

/// `[rows, cols]` and strides of a rank-2 primitive.
fn dims(t: &Primitive) -> Result<([usize; 2], [usize; 2]), String> {
    match (&t.meta.shape()[..], &t.meta.strides()[..]) {
        ([r, c], [s0, s1]) => Ok(([*r, *c], [*s0, *s1])),
        (s, _) => Err(format!("rank {}", s.len())),
    }
}

/// The leading dimension of a row-major result-shaped matrix (`out`, `add`).
fn row_major(what: &str, t: &Primitive, shape: [usize; 2]) -> Result<i64, String> {
    let (s, st) = dims(t)?;
    if s != shape {
        return Err(format!("{what} {s:?} for a {shape:?} result"));
    }
    match layout(s, st) {
        Some((cudarc::cublas::sys::cublasOperation_t::CUBLAS_OP_N, ld)) => Ok(ld as i64),
        _ => Err(format!("{what} strides {st:?}")),
    }
}

/// `out = lhs · rhs + bias + add` on cuBLASLt: `lhs [m, k]` and `rhs [k, n]` of one float format, row- or
/// column-major; `out`, `add` and `bias` in the result's format (f32, or the operands' own), `out` and
/// `add` row-major. Anything cuBLASLt cannot take says why, before anything is launched.
pub(super) fn launch(
    lhs: &Primitive,
    rhs: &Primitive,
    out: &Primitive,
    epilogue: Epilogue<'_>,
    kernels: &Kernels,
) -> Result<(), String> {
    if lhs.dtype != rhs.dtype {
        return Err(format!("mixed operands {:?} × {:?}", lhs.dtype, rhs.dtype));
    }
    let (data, compute) = types(lhs.dtype)?;
    let (written, _) = types(out.dtype)?;
    if out.dtype != DType::F32 && out.dtype != lhs.dtype {
        return Err(format!("{:?} result of {:?} operands", out.dtype, lhs.dtype));
    }
    let ((ls, lst), (rs, rst)) = (dims(lhs)?, dims(rhs)?);
    let (m, k, n) = (ls[0], ls[1], rs[1]);
    if rs[0] != k || m == 0 || n == 0 || k == 0 {
        return Err(format!("shapes {ls:?} × {rs:?}"));
    }
    let ldd = row_major("result", out, [m, n])?;
    let ldc = match epilogue.add {
        Some(add) if add.dtype != out.dtype => {
            return Err(format!("{:?} rows added to a {:?} result", add.dtype, out.dtype));
        }
        Some(add) => row_major("added rows", add, [m, n])?,
        None => ldd,
    };
    if let Some(bias) = epilogue.bias {
        let (shape, strides) = (bias.meta.shape(), bias.meta.strides());
        if bias.dtype != out.dtype || shape[..] != [n] || strides[..] != [1] {
            return Err(format!(
                "bias {:?} {shape:?} for a {:?} result of {n} columns",
                bias.dtype, out.dtype
            ));
        }
    }
    let (a_op, lda) = layout(rs, rst).ok_or_else(|| format!("rhs strides {rst:?}"))?;
    let (b_op, ldb) = layout(ls, lst).ok_or_else(|| format!("lhs strides {lst:?}"))?;
    int("ld", lda.max(ldb).max(ldc as usize).max(ldd as usize))?;
    // Row-major out = lhs · rhs is column-major outᵀ = rhsᵀ · lhsᵀ: cuBLAS's A is rhs, its B is lhs.
    let (a, _keep_a) = pointer(rhs)?;
    let (b, _keep_b) = pointer(lhs)?;
    let (d, _keep_d) = pointer(out)?;
    let (c, _keep_c) = match epilogue.add {
        Some(add) => {
            let (p, keep) = pointer(add)?;
            (p, Some(keep))
        }
        None => (d, None),
    };
    let bias = match epilogue.bias {
        Some(bias) => {
            let (p, keep) = pointer(bias)?;
            // cuBLASLt reads the bias in vectors; no preference says how aligned it is.
            if alignment(p) < 16 {
                return Err(format!("a bias at {p:#x}, not 16-byte aligned"));
            }
            Some((p, keep))
        }
        None => None,
    };
    let a = Operand {
        ptr: a,
        op: a_op,
        ld: int("lda", lda)?,
    };
    let b = Operand {
        ptr: b,
        op: b_op,
        ld: int("ldb", ldb)?,
    };
    let key = Key {
        mnk: [n as u64, m as u64, k as u64],
        ops: [a.op as i32, b.op as i32],
        lds: [i64::from(a.ld), i64::from(b.ld), ldc, ldd],
        data,
        out: written,
        compute,
        bias: bias.is_some(),
        align: [alignment(a.ptr), alignment(b.ptr), alignment(c), alignment(d)],
    };
    let beta = if epilogue.add.is_some() { 1.0f32 } else { 0.0 };
    let bias_ptr = bias.as_ref().map(|(p, _)| *p);
    with_cached(&HANDLES, lhs, "cuBLASLt", Lt::new, |handle| {
        let (h, workspace) = (handle.handle, handle.workspace);
        let plan = handle.plan(key)?;
        let algo = plan.algo.as_ref().ok_or("no algorithm")?;
        if let Some(p) = bias_ptr {
            set(
                plan.desc,
                sys::cublasLtMatmulDescAttributes_t::CUBLASLT_MATMUL_DESC_BIAS_POINTER,
                &p,
            )?;
        }
        let l = &plan.layouts;
        on_stream(lhs, kernels, |stream| {
            let one = 1.0f32;
            // SAFETY: every pointer is a live burn buffer of the shape, strides and type the layouts
            // describe (checked above), held until cubecl's stream has passed the product; the workspace
            // is this handle's; the scalars are f32 as the scale type says.
            unsafe {
                lt::matmul(
                    h,
                    plan.desc,
                    (&one as *const f32).cast::<c_void>(),
                    (&beta as *const f32).cast::<c_void>(),
                    a.ptr as *const c_void,
                    l[0],
                    b.ptr as *const c_void,
                    l[1],
                    c as *const c_void,
                    l[2],
                    d as *mut c_void,
                    l[3],
                    algo,
                    workspace as *mut c_void,
                    WORKSPACE,
                    stream.cast(),
                )
            }
            .map_err(err("cublasLtMatmul"))
        })
    })
}

#[cfg(test)]
mod tests {
    use super::alignment;

    #[test]
    fn alignment_is_the_largest_power_of_two_up_to_256() {
        assert_eq!(alignment(0x1000), 256);
        assert_eq!(alignment(0x1010), 16);
        assert_eq!(alignment(0x1004), 4);
        assert_eq!(alignment(0x1001), 1);
    }
}
