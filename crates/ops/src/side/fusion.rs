//! The plumbing of the custom fusion operations whose work runs on the side stream: the backend and
//! tensor types their handles hold, their inputs made contiguous, their outputs allocated packed and
//! registered, and [`register`], which puts a [`SidePass`] on burn-fusion's stream.

use burn::backend::Cuda;
use burn::cubecl::cuda::CudaRuntime;
use burn::tensor::ops::FloatTensor;
use burn::tensor::{DType, Shape};
use burn_cubecl::CubeBackend;
use burn_cubecl::fusion::FusionCubeRuntime;
use burn_cubecl::kernel::into_contiguous;
use burn_cubecl::ops::numeric::empty_device_contiguous_dtype;
use burn_cubecl::tensor::CubeTensor;
use burn_fusion::stream::{Operation, OperationStreams};
use burn_ir::{CustomOpIr, HandleContainer, OperationIr, TensorIr};

/// The cubecl backend under burn-fusion's `Cuda`: what a custom fusion operation's handles hold.
pub(crate) type Inner = CubeBackend<CudaRuntime, f32, i32, u8>;
/// A tensor of [`Inner`].
pub(crate) type Primitive = CubeTensor<CudaRuntime>;
/// The handles a custom fusion operation reads its inputs from and registers its outputs in.
pub(crate) type Handles =
    HandleContainer<<FusionCubeRuntime<CudaRuntime> as burn_fusion::FusionRuntime>::FusionHandle>;

/// `t`'s fusion primitive (a custom operation's input).
pub(crate) fn fused<const D: usize>(t: burn::tensor::Tensor<Cuda, D>) -> FloatTensor<Cuda> {
    t.into_primitive().tensor()
}

/// `t`'s cubecl primitive (a custom operation's output computed with burn operations on [`Inner`]).
pub(crate) fn inner<const D: usize>(t: burn::tensor::Tensor<Inner, D>) -> Primitive {
    t.into_primitive().tensor()
}

/// The `N` inputs of the custom operation `desc`, each made contiguous (whatever its number of outputs,
/// which [`register_outputs`] checks against what the pass computed).
pub(crate) fn contiguous_inputs<const N: usize>(handles: &mut Handles, desc: &CustomOpIr) -> [Primitive; N] {
    let Ok(inputs) = <&[TensorIr; N]>::try_from(desc.inputs.as_slice()) else {
        unreachable!(
            "{} was registered with {} inputs, read as {N}",
            desc.id,
            desc.inputs.len()
        )
    };
    inputs
        .each_ref()
        .map(|t| into_contiguous(handles.get_float_tensor::<Inner>(t)))
}

/// Registers `outputs` as the outputs of the custom operation `desc`, in order.
pub(crate) fn register_outputs(handles: &mut Handles, desc: &CustomOpIr, outputs: Vec<Primitive>) {
    // A pass that computed another number of results than it was registered with would leave a later
    // operation without its input's handle; a pass's output list is fixed by its code, so this cannot
    // follow from data.
    assert_eq!(
        outputs.len(),
        desc.outputs.len(),
        "{} computed another number of results than it was registered with",
        desc.id
    );
    for (ir, t) in desc.outputs.iter().zip(outputs) {
        handles.register_float_tensor::<Inner>(&ir.id, t);
    }
}

/// One pass of a custom operation on the fusion stream (a layer norm's forward pass, …).
pub(crate) trait SidePass: std::fmt::Debug + Send + Sync + 'static {
    /// Reads the inputs `desc` names from `handles` and computes the outputs, in `desc`'s order.
    fn outputs(&self, handles: &mut Handles, desc: &CustomOpIr) -> Vec<Primitive>;
}

/// A [`SidePass`] as the fusion stream runs it: its outputs registered under `desc`'s ids.
#[derive(Debug)]
struct SideOp<P> {
    desc: CustomOpIr,
    pass: P,
}

impl<P: SidePass> Operation<FusionCubeRuntime<CudaRuntime>> for SideOp<P> {
    fn execute(&self, handles: &mut Handles) {
        let outputs = self.pass.outputs(handles, &self.desc);
        register_outputs(handles, &self.desc, outputs);
    }
}

/// Registers `pass` on the fusion stream as the custom operation `id`: `inputs` in, f32 outputs of
/// `shapes` out.
pub(crate) fn register<P: SidePass, const I: usize, const N: usize>(
    id: &'static str,
    inputs: [FloatTensor<Cuda>; I],
    shapes: [Vec<usize>; N],
    pass: P,
) -> [FloatTensor<Cuda>; N] {
    register_many(id, inputs.into(), shapes.into(), pass)
        .try_into()
        .unwrap_or_else(|_| unreachable!("the operation was described with {N} outputs"))
}

/// [`register`] for any number of inputs and outputs (at least one input).
pub(crate) fn register_many<P: SidePass>(
    id: &'static str,
    inputs: Vec<FloatTensor<Cuda>>,
    shapes: Vec<Vec<usize>>,
    pass: P,
) -> Vec<FloatTensor<Cuda>> {
    let typed = shapes.into_iter().map(|s| (s, DType::F32)).collect();
    register_typed(id, inputs, typed, pass)
}

/// [`register_many`] with each output's type given beside its shape.
pub(crate) fn register_typed<P: SidePass>(
    id: &'static str,
    inputs: Vec<FloatTensor<Cuda>>,
    outputs: Vec<(Vec<usize>, DType)>,
    pass: P,
) -> Vec<FloatTensor<Cuda>> {
    let Some(client) = inputs.first().map(|t| t.client.clone()) else {
        unreachable!("{id} is registered with inputs")
    };
    let outs: Vec<TensorIr> = outputs
        .into_iter()
        .map(|(s, dtype)| TensorIr::uninit(client.create_empty_handle(), Shape::from(s), dtype))
        .collect();
    let streams = OperationStreams::with_inputs(inputs.iter());
    let irs: Vec<TensorIr> = inputs.into_iter().map(|p| p.into_ir()).collect();
    let desc = CustomOpIr::new(id, &irs, &outs);
    client.register(streams, OperationIr::Custom(desc.clone()), SideOp { desc, pass })
}

/// A total `[d]` laid out as `rows` rows of partial sums `[rows, d]`, the total in the first and zeros
/// after: the shape a kernel's per-group column sums are registered with (the layer norm's, the bias +
/// GELU's), for a fallback that computes the total at once.
pub(crate) fn as_partial_sums(total: burn::tensor::Tensor<Inner, 1>, rows: usize) -> Primitive {
    let d = total.dims()[0];
    let zeros = burn::tensor::Tensor::<Inner, 2>::zeros([rows - 1, d], &total.device());
    inner(burn::tensor::Tensor::cat(vec![total.reshape([1, d]), zeros], 0))
}

/// An uninitialised f32 tensor of `shape` on `like`'s device, packed row-major as the kernels write it.
/// (burn's `empty_device_dtype` pads each innermost row to an aligned pitch: a `[rows, 1028]` tensor has
/// rows 1,088 apart, a `[.., 6]` one rows 8 apart, which a kernel indexing `row · width` would misplace.)
pub(crate) fn empty_f32(like: &Primitive, shape: Vec<usize>) -> Primitive {
    empty_packed(like, shape, DType::F32)
}

/// [`empty_f32`] of any type.
pub(crate) fn empty_packed(like: &Primitive, shape: Vec<usize>, dtype: DType) -> Primitive {
    empty_device_contiguous_dtype(
        like.client.clone(),
        like.device.clone(),
        Shape::from(shape),
        dtype,
    )
}
