//! [`FusedAttention`] for `Cuda` (burn-fusion over the cubecl backend): each pass is a custom operation in
//! the fusion stream that launches the kernels of `kernels.rs` (or flash2's) on the operands as they lie in
//! memory (any strides) and writes its results in the operands' format where flash2 runs it (bf16 with the
//! bf16 presets: the output and the gradients feed bf16 products), f32 otherwise (the fused kernels'
//! results, cast where flash2 was chosen but failed to launch); the log-sum-exp is always f32. The backward
//! pass writes the keys' and values' gradients as one `[b, lk, 2·h, d]`, the layout of the kv product's
//! gradient.

use super::flash2;
use super::kernels;
use super::{
    AttentionKernel, BLOCK, FusedAttention, fell_back, merge_kv, shared_bytes, tiled_backward_pass,
    tiled_forward_pass, unfit,
};
use crate::format::Precision;
use crate::format::float;
use crate::format::float_format;
use crate::kernels::Kernels;
use crate::side::{Handles, Inner, Primitive, empty_f32};
use crate::tiled::softmax_delta;
use burn::backend::Cuda;
use burn::cubecl::Runtime;
use burn::cubecl::cuda::CudaRuntime;
use burn::tensor::ops::FloatTensorOps;
use burn::tensor::{DType, Shape, Tensor};
use burn_cubecl::fusion::FusionCubeRuntime;
use burn_fusion::stream::{Operation, OperationStreams};
use burn_ir::{CustomOpIr, OperationIr, TensorIr};
use cubecl::prelude::{CubeCount, CubeDim, CubePrimitive, StorageType};
use cubecl::tf32;

/// Why the kernels cannot take these operands, if they cannot.
fn refused(
    q: &Tensor<Cuda, 4>,
    k: &Tensor<Cuda, 4>,
    v: &Tensor<Cuda, 4>,
    kernels: &Kernels,
) -> Option<String> {
    let [b, h, _, d] = q.dims();
    if let Some(why) = unfit(d) {
        return Some(why);
    }
    // The launch grid's z and y extents.
    if b > 65_535 || h > 65_535 {
        return Some(format!(
            "{b} sequences of {h} heads (the launch grid takes 65,535 of each)"
        ));
    }
    let dt = q.dtype();
    if !matches!(dt, DType::F32 | DType::BF16) || k.dtype() != dt || v.dtype() != dt {
        return Some(format!(
            "operands {:?}, {:?}, {:?} (the fused kernels take f32 or bf16, all alike)",
            dt,
            k.dtype(),
            v.dtype()
        ));
    }
    if v.dims()[3] != d {
        return Some(format!("value size {} ≠ query size {d}", v.dims()[3]));
    }
    let need = shared_bytes(d, dt.size(), kernels.attention_step);
    let have = CudaRuntime::client(&q.device())
        .properties()
        .hardware
        .max_shared_memory_size;
    (need > have)
        .then(|| format!("head size {d} in {dt:?}: {need} bytes of shared memory, the device allows {have}"))
}

/// The products' tile format and depth for operands of `dtype`: TF32 16×16×8 for f32, bf16 16×16×16.
fn tile_format(dtype: DType) -> (StorageType, usize) {
    match dtype {
        DType::BF16 => (dtype.into(), 16),
        _ => (tf32::as_type_native_unchecked().storage_type(), 8),
    }
}

/// Registers pass `kind` on the fusion stream: `inputs` in, outputs of `shapes` and types out.
fn register<const N: usize>(
    kind: Kind,
    causal: bool,
    flash2: bool,
    kernels: &Kernels,
    inputs: &[&Tensor<Cuda, 4>],
    shapes: [(Shape, DType); N],
) -> [Tensor<Cuda, 4>; N] {
    let prims: Vec<_> = inputs
        .iter()
        .map(|t| (*t).clone().into_primitive().tensor())
        .collect();
    let client = prims[0].client.clone();
    let outs: Vec<TensorIr> = shapes
        .into_iter()
        .map(|(s, dtype)| TensorIr::uninit(client.create_empty_handle(), s, dtype))
        .collect();
    let streams = OperationStreams::with_inputs(prims.iter());
    let irs: Vec<TensorIr> = prims.into_iter().map(|p| p.into_ir()).collect();
    let id = match kind {
        Kind::Forward => "umgen_flash_forward",
        Kind::Backward => "umgen_flash_backward",
    };
    let desc = CustomOpIr::new(id, &irs, &outs);
    let pass = Pass {
        desc: desc.clone(),
        causal,
        kind,
        flash2,
        kernels: *kernels,
    };
    let out = client.register(streams, OperationIr::Custom(desc), pass);
    let tensors: Vec<Tensor<Cuda, 4>> = out.into_iter().map(float).collect();
    tensors
        .try_into()
        .unwrap_or_else(|_| unreachable!("the operation was described with {N} outputs"))
}

impl FusedAttention for Cuda {
    fn attention_forward(
        q: Tensor<Self, 4>,
        k: Tensor<Self, 4>,
        v: Tensor<Self, 4>,
        causal: bool,
        precision: Precision,
        kernels: &Kernels,
    ) -> (Tensor<Self, 4>, Tensor<Self, 4>) {
        if kernels.attention == AttentionKernel::Tiled {
            return tiled_forward_pass(q, k, v, causal, precision, kernels);
        }
        if let Some(why) = refused(&q, &k, &v, kernels) {
            fell_back("fused", &why, "tiled");
            return tiled_forward_pass(q, k, v, causal, precision, kernels);
        }
        let [b, h, lq, d] = q.dims();
        let flash2 = use_flash2(&q, kernels);
        let [out, lse] = register(
            Kind::Forward,
            causal,
            flash2,
            kernels,
            &[&q, &k, &v],
            [
                (Shape::new([b, h, lq, d]), results(flash2, &q)),
                (Shape::new([b, h, lq, 1]), DType::F32),
            ],
        );
        (out, lse)
    }

    fn attention_backward(
        q: Tensor<Self, 4>,
        k: Tensor<Self, 4>,
        v: Tensor<Self, 4>,
        out: Tensor<Self, 4>,
        lse: Tensor<Self, 4>,
        dout: Tensor<Self, 4>,
        causal: bool,
        precision: Precision,
        kernels: &Kernels,
    ) -> (Tensor<Self, 4>, Tensor<Self, 4>, Tensor<Self, 4>) {
        if backward_tiled(&q, &k, &v, kernels) {
            return tiled_backward_pass(q, k, v, out, lse, dout, causal, precision, kernels);
        }
        let h = q.dims()[1];
        let (dq, dkv) = backward_merged(q, k, v, out, lse, dout, causal, precision, kernels);
        // Views of the merged gradient: `[b, lk, h, d]` twice, heads first.
        let (dk, dv) = (dkv.clone().narrow(2, 0, h), dkv.narrow(2, h, h));
        (dq, dk.swap_dims(1, 2), dv.swap_dims(1, 2))
    }

    fn attention_backward_kv(
        q: Tensor<Self, 4>,
        k: Tensor<Self, 4>,
        v: Tensor<Self, 4>,
        out: Tensor<Self, 4>,
        lse: Tensor<Self, 4>,
        dout: Tensor<Self, 4>,
        causal: bool,
        precision: Precision,
        kernels: &Kernels,
    ) -> (Tensor<Self, 4>, Tensor<Self, 3>) {
        if backward_tiled(&q, &k, &v, kernels) {
            let (dq, dk, dv) = tiled_backward_pass(q, k, v, out, lse, dout, causal, precision, kernels);
            return (dq, merge_kv(dk, dv));
        }
        let (dq, dkv) = backward_merged(q, k, v, out, lse, dout, causal, precision, kernels);
        let [b, lk, h2, d] = dkv.dims();
        (dq, dkv.reshape([b, lk, h2 * d]))
    }
}

/// Whether a backward pass runs the tiled passes: where they are selected, or where the kernels refuse the
/// operands (the forward pass counted that fallback).
fn backward_tiled(q: &Tensor<Cuda, 4>, k: &Tensor<Cuda, 4>, v: &Tensor<Cuda, 4>, kernels: &Kernels) -> bool {
    kernels.attention == AttentionKernel::Tiled || refused(q, k, v, kernels).is_some()
}

/// The backward pass as one custom operation: dq `[b, h, lq, d]` and the keys' and values' gradients as one
/// `[b, lk, 2·h, d]` (the keys' heads, then the values'), which flash2 writes in place and the fused
/// kernels' results are copied into.
#[allow(clippy::too_many_arguments)]
fn backward_merged(
    q: Tensor<Cuda, 4>,
    k: Tensor<Cuda, 4>,
    v: Tensor<Cuda, 4>,
    out: Tensor<Cuda, 4>,
    lse: Tensor<Cuda, 4>,
    dout: Tensor<Cuda, 4>,
    causal: bool,
    precision: Precision,
    kernels: &Kernels,
) -> (Tensor<Cuda, 4>, Tensor<Cuda, 4>) {
    let delta = softmax_delta(dout.clone(), out);
    let dout = crate::format::operand(dout, precision);
    let [b, h, lq, d] = q.dims();
    let lk = k.dims()[2];
    let flash2 = use_flash2(&q, kernels);
    let dtype = results(flash2, &q);
    let [dq, dkv] = register(
        Kind::Backward,
        causal,
        flash2,
        kernels,
        &[&q, &k, &v, &dout, &lse, &delta],
        [
            (Shape::new([b, h, lq, d]), dtype),
            (Shape::new([b, lk, 2 * h, d]), dtype),
        ],
    );
    (dq, dkv)
}

/// The format of a pass's results other than the log-sum-exp: flash2 writes the operands' own, the fused
/// kernels f32.
fn results(flash2: bool, q: &Tensor<Cuda, 4>) -> DType {
    if flash2 { q.dtype() } else { DType::F32 }
}

/// Which pass.
#[derive(Debug, Clone, Copy)]
enum Kind {
    /// q, k, v in; output and log-sum-exp out.
    Forward,
    /// q, k, v, dout, log-sum-exp, delta in; dq and the merged dk, dv (`[b, lk, 2·h, d]`) out.
    Backward,
}

/// Whether the `flash2` kernels run a pass on `q`'s operands: chosen, and taking its head size and type
/// (otherwise the fused kernels run it, counted as a fallback).
fn use_flash2(q: &Tensor<Cuda, 4>, kernels: &Kernels) -> bool {
    if kernels.attention != AttentionKernel::Flash2 {
        return false;
    }
    match flash2::unfit(q.dims()[3], q.dtype()) {
        Some(why) => {
            fell_back("flash2", &why, "fused");
            false
        }
        None => true,
    }
}

/// One pass as the fusion stream runs it.
#[derive(Debug)]
struct Pass {
    desc: CustomOpIr,
    causal: bool,
    kind: Kind,
    /// The `flash2` kernels run it (the fused ones if they fail to launch).
    flash2: bool,
    /// The fused kernels' step, the stream and the launching thread.
    kernels: Kernels,
}

impl Operation<FusionCubeRuntime<CudaRuntime>> for Pass {
    fn execute(&self, handles: &mut Handles) {
        let outputs = match self.kind {
            Kind::Forward => {
                let ([q, k, v], _) = self.desc.as_fixed::<3, 2>();
                let [q, k, v] = [q, k, v].map(|t| handles.get_float_tensor::<Inner>(t));
                let thread = self.kernels.launch_thread;
                self.flash2_or(
                    || {
                        crate::side::on_device_thread(&q, thread, || {
                            flash2::launch(&q, &k, &v, None, self.causal, &self.kernels)
                        })
                    },
                    || forward(&q, &k, &v, self.causal, self.kernels.attention_step),
                )
            }
            Kind::Backward => {
                let (inputs, _) = self.desc.as_fixed::<6, 2>();
                let [q, k, v, dout, lse, delta] =
                    inputs.each_ref().map(|t| handles.get_float_tensor::<Inner>(t));
                let thread = self.kernels.launch_thread;
                self.flash2_or(
                    || {
                        crate::side::on_device_thread(&q, thread, || {
                            flash2::launch(
                                &q,
                                &k,
                                &v,
                                Some([&dout, &lse, &delta]),
                                self.causal,
                                &self.kernels,
                            )
                        })
                    },
                    || {
                        backward(
                            &q,
                            &k,
                            &v,
                            &dout,
                            &lse,
                            &delta,
                            self.causal,
                            self.kernels.attention_step,
                        )
                    },
                )
            }
        };
        crate::side::register_outputs(handles, &self.desc, outputs);
    }
}

impl Pass {
    /// The `flash2` kernels' results where this pass runs them and they launch; otherwise (a failure
    /// counted as a fallback) the fused kernels', cast to the formats the pass registered.
    fn flash2_or(
        &self,
        flash2: impl FnOnce() -> Result<Vec<Primitive>, String>,
        fused: impl FnOnce() -> Vec<Primitive>,
    ) -> Vec<Primitive> {
        if self.flash2 {
            match flash2() {
                Ok(results) => return results,
                Err(why) => fell_back("flash2", &why, "fused"),
            }
        }
        fused()
            .into_iter()
            .zip(&self.desc.outputs)
            .map(|(t, registered)| {
                if t.dtype == registered.dtype {
                    t
                } else {
                    Inner::float_cast(t, float_format(registered.dtype))
                }
            })
            .collect()
    }
}

/// Launch geometry: one cube per block of `rows` rows of each (sequence, head); four planes of 32.
fn geometry(rows: usize, b: usize, h: usize) -> (CubeCount, CubeDim) {
    let blocks = rows.div_ceil(BLOCK) as u32;
    (
        CubeCount::Static(blocks, h as u32, b as u32),
        CubeDim::new_2d(32, 4),
    )
}

/// `(1/√d, lk − lq)`: the score scale and the causal mask's offset.
fn scale_and_offset(q: &Primitive, k: &Primitive) -> (f32, usize) {
    let (lq, d) = (q.meta.shape()[2], q.meta.shape()[3]);
    let lk = k.meta.shape()[2];
    (1.0 / (d as f32).sqrt(), lk.saturating_sub(lq))
}

fn forward(q: &Primitive, k: &Primitive, v: &Primitive, causal: bool, step: usize) -> Vec<Primitive> {
    let [b, h, lq, d] = dims(q);
    let out = empty_f32(q, vec![b, h, lq, d]);
    let lse = empty_f32(q, vec![b, h, lq, 1]);
    let (scale, off) = scale_and_offset(q, k);
    let (format, kstep) = tile_format(q.dtype);
    let (count, dim) = geometry(lq, b, h);
    kernels::forward_pass::forward::launch::<CudaRuntime>(
        &q.client,
        count,
        dim,
        q.clone().into_tensor_arg(),
        k.clone().into_tensor_arg(),
        v.clone().into_tensor_arg(),
        out.clone().into_tensor_arg(),
        lse.clone().into_tensor_arg(),
        scale,
        off,
        causal,
        d,
        kstep,
        step,
        [q.dtype.into(), format],
    );
    vec![out, lse]
}

#[allow(clippy::too_many_arguments)]
fn backward(
    q: &Primitive,
    k: &Primitive,
    v: &Primitive,
    dout: &Primitive,
    lse: &Primitive,
    delta: &Primitive,
    causal: bool,
    step: usize,
) -> Vec<Primitive> {
    let [b, h, lq, d] = dims(q);
    let lk = k.meta.shape()[2];
    let dq = empty_f32(q, vec![b, h, lq, d]);
    let dk = empty_f32(q, vec![b, h, lk, d]);
    let dv = empty_f32(q, vec![b, h, lk, d]);
    let merged = || {
        let dkv = merge_kv::<Inner>(float(dk.clone()), float(dv.clone()));
        crate::side::inner(dkv.reshape([b, lk, 2 * h, d]))
    };
    let (scale, off) = scale_and_offset(q, k);
    let (format, kstep) = tile_format(q.dtype);
    let arg = |t: &Primitive| t.clone().into_tensor_arg();
    let (count, dim) = geometry(lk, b, h);
    kernels::backward_pass::backward_kv::launch::<CudaRuntime>(
        &q.client,
        count,
        dim,
        arg(q),
        arg(k),
        arg(v),
        arg(dout),
        arg(lse),
        arg(delta),
        arg(&dk),
        arg(&dv),
        scale,
        off,
        causal,
        d,
        kstep,
        step,
        [q.dtype.into(), format],
    );
    let (count, dim) = geometry(lq, b, h);
    kernels::backward_pass::backward_q::launch::<CudaRuntime>(
        &q.client,
        count,
        dim,
        arg(q),
        arg(k),
        arg(v),
        arg(dout),
        arg(lse),
        arg(delta),
        arg(&dq),
        scale,
        off,
        causal,
        d,
        kstep,
        step,
        [q.dtype.into(), format],
    );
    vec![dq, merged()]
}

fn dims(t: &Primitive) -> [usize; 4] {
    let s = t.meta.shape();
    [s[0], s[1], s[2], s[3]]
}
