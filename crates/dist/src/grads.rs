//! Data-parallel steps on a module: broadcast its parameters from rank 0, and average gradients over
//! ranks in buckets (one collective per ~`bucket_bytes`, not per tensor); check that ranks agree on a
//! value.

use crate::error::{DistError, Result};
use crate::group::ProcessGroup;
use burn::module::{AutodiffModule, ModuleMapper, ModuleVisitor, Param, ParamId};
use burn::optim::GradientsParams;
use burn::tensor::Tensor;
use burn::tensor::backend::{AutodiffBackend, Backend};

/// Float parameters in module order: ids and shapes.
struct Shapes {
    params: Vec<(ParamId, Vec<usize>)>,
}

impl<B: AutodiffBackend> ModuleVisitor<B> for Shapes {
    fn visit_float<const D: usize>(&mut self, param: &Param<Tensor<B, D>>) {
        self.params.push((param.id, param.val().dims().to_vec()));
    }
}

pub(crate) fn shapes<B: AutodiffBackend, M: AutodiffModule<B>>(model: &M) -> Vec<(ParamId, Vec<usize>)> {
    let mut v = Shapes { params: Vec::new() };
    model.visit(&mut v);
    v.params
}

/// Index ranges of `sizes` grouped into buckets of at least `bucket_elems` (the last may be smaller).
pub(crate) fn buckets(sizes: &[usize], bucket_elems: usize) -> Vec<std::ops::Range<usize>> {
    buckets_of(sizes, bucket_elems, usize::MAX)
}

/// Index ranges of `sizes`, in order, each summing to at least `elems` or holding `count` entries (the
/// last may hold less).
pub(crate) fn buckets_of(sizes: &[usize], elems: usize, count: usize) -> Vec<std::ops::Range<usize>> {
    let mut out = Vec::new();
    let (mut start, mut acc) = (0, 0);
    for (i, s) in sizes.iter().enumerate() {
        acc += s;
        if acc >= elems.max(1) || i + 1 - start >= count.max(1) {
            out.push(start..i + 1);
            start = i + 1;
            acc = 0;
        }
    }
    if start < sizes.len() {
        out.push(start..sizes.len());
    }
    out
}

/// Runs `op` on the flattened parts in buckets and returns the parts, reshaped to their sizes.
fn bucketed<B: Backend>(
    parts: Vec<Tensor<B, 1>>,
    bucket_bytes: usize,
    mut op: impl FnMut(Tensor<B, 1>) -> Result<Tensor<B, 1>>,
) -> Result<Vec<Tensor<B, 1>>> {
    let sizes: Vec<usize> = parts.iter().map(|t| t.dims()[0]).collect();
    let mut parts: Vec<Option<Tensor<B, 1>>> = parts.into_iter().map(Some).collect();
    let mut out = Vec::with_capacity(sizes.len());
    for range in buckets(&sizes, bucket_bytes / 4) {
        let chunk: Vec<Tensor<B, 1>> = range.filter_map(|i| parts[i].take()).collect();
        out.extend(as_one(chunk, &mut op)?);
    }
    Ok(out)
}

/// Runs `op` on `parts` concatenated (one collective) and returns the result cut back into the parts'
/// sizes.
pub(crate) fn as_one<B: Backend>(
    mut parts: Vec<Tensor<B, 1>>,
    op: &mut impl FnMut(Tensor<B, 1>) -> Result<Tensor<B, 1>>,
) -> Result<Vec<Tensor<B, 1>>> {
    let sizes: Vec<usize> = parts.iter().map(|t| t.dims()[0]).collect();
    let flat = match parts.len() {
        0 => return Ok(parts),
        1 => parts.swap_remove(0),
        _ => Tensor::cat(parts, 0),
    };
    let reduced = op(flat)?;
    let mut offset = 0;
    Ok(sizes
        .into_iter()
        .map(|n| {
            offset += n;
            reduced.clone().narrow(0, offset - n, n)
        })
        .collect())
}

/// Averages `grads` over the ranks of `group`: gradients of `model`'s float parameters, in module order,
/// concatenated into buckets of about `bucket_bytes`. A parameter without a gradient on this rank
/// contributes zeros (every rank must reduce the same buffers) and is registered with the average.
pub fn all_reduce_grads<B: AutodiffBackend, M: AutodiffModule<B>>(
    model: &M,
    mut grads: GradientsParams,
    group: &mut dyn ProcessGroup<B::InnerBackend>,
    bucket_bytes: usize,
) -> Result<GradientsParams> {
    if group.world_size() == 1 {
        return Ok(grads);
    }
    let params = shapes::<B, M>(model);
    let device = model.devices().into_iter().next().unwrap_or_default();
    let parts: Vec<Tensor<B::InnerBackend, 1>> = params
        .iter()
        .map(|(id, shape)| {
            let n: usize = shape.iter().product();
            take_flat::<B>(&mut grads, *id, shape.len()).unwrap_or_else(|| Tensor::zeros([n], &device))
        })
        .collect();
    let reduced = bucketed(parts, bucket_bytes, |t| group.all_reduce_mean(t))?;
    for ((id, shape), t) in params.iter().zip(reduced) {
        register::<B>(&mut grads, *id, t, shape);
    }
    Ok(grads)
}

/// Removes a gradient of rank `d` and flattens it.
pub(crate) fn take_flat<B: AutodiffBackend>(
    grads: &mut GradientsParams,
    id: ParamId,
    d: usize,
) -> Option<Tensor<B::InnerBackend, 1>> {
    fn flat<B: Backend, const D: usize>(g: &mut GradientsParams, id: ParamId) -> Option<Tensor<B, 1>> {
        g.remove::<B, D>(id).map(|t| t.flatten::<1>(0, D - 1))
    }
    match d {
        1 => flat::<B::InnerBackend, 1>(grads, id),
        2 => flat::<B::InnerBackend, 2>(grads, id),
        3 => flat::<B::InnerBackend, 3>(grads, id),
        4 => flat::<B::InnerBackend, 4>(grads, id),
        5 => flat::<B::InnerBackend, 5>(grads, id),
        6 => flat::<B::InnerBackend, 6>(grads, id),
        _ => None,
    }
}

pub(crate) fn register<B: AutodiffBackend>(
    grads: &mut GradientsParams,
    id: ParamId,
    t: Tensor<B::InnerBackend, 1>,
    shape: &[usize],
) {
    match shape.len() {
        1 => grads.register(id, t.reshape::<1, _>([shape[0]])),
        2 => grads.register(id, t.reshape::<2, _>([shape[0], shape[1]])),
        3 => grads.register(id, t.reshape::<3, _>([shape[0], shape[1], shape[2]])),
        4 => grads.register(id, t.reshape::<4, _>([shape[0], shape[1], shape[2], shape[3]])),
        5 => grads.register(
            id,
            t.reshape::<5, _>([shape[0], shape[1], shape[2], shape[3], shape[4]]),
        ),
        6 => grads.register(
            id,
            t.reshape::<6, _>([shape[0], shape[1], shape[2], shape[3], shape[4], shape[5]]),
        ),
        _ => {}
    }
}

/// Replaces float parameters, in module order, with given flat values.
pub(crate) struct Replace<B: AutodiffBackend> {
    pub(crate) values: std::vec::IntoIter<Tensor<B::InnerBackend, 1>>,
}

impl<B: AutodiffBackend> ModuleMapper<B> for Replace<B> {
    fn map_float<const D: usize>(&mut self, param: Param<Tensor<B, D>>) -> Param<Tensor<B, D>> {
        match self.values.next() {
            Some(v) => param.map(|t| {
                let grad = t.is_require_grad();
                let shape = t.shape();
                Tensor::<B, D>::from_inner(v.reshape(shape)).set_require_grad(grad)
            }),
            None => param,
        }
    }
}

/// Float parameters' flat values, in module order.
pub(crate) struct Flat<B: AutodiffBackend> {
    pub(crate) values: Vec<Tensor<B::InnerBackend, 1>>,
}

impl<B: AutodiffBackend> ModuleVisitor<B> for Flat<B> {
    fn visit_float<const D: usize>(&mut self, param: &Param<Tensor<B, D>>) {
        self.values.push(param.val().inner().flatten::<1>(0, D - 1));
    }
}

/// `model` with rank 0's parameter values on every rank (in buckets of about `bucket_bytes`).
pub fn broadcast_module<B: AutodiffBackend, M: AutodiffModule<B>>(
    model: M,
    group: &mut dyn ProcessGroup<B::InnerBackend>,
    bucket_bytes: usize,
) -> Result<M> {
    if group.world_size() == 1 {
        return Ok(model);
    }
    let mut flat = Flat::<B> { values: Vec::new() };
    model.visit(&mut flat);
    let values = bucketed(flat.values, bucket_bytes, |t| group.broadcast(t, 0))?;
    Ok(model.map(&mut Replace::<B> {
        values: values.into_iter(),
    }))
}

/// Checks that every rank holds the same `value` (below 2^48), e.g. the step a resumed run starts from.
/// Every rank learns whether any differs, so all fail together (a rank that differs names its value and
/// rank 0's) instead of drifting into mismatched collectives that only a timeout ends.
pub fn same_on_all_ranks<B: Backend>(
    group: &mut dyn ProcessGroup<B>,
    value: u64,
    what: &str,
    device: &B::Device,
) -> Result<()> {
    if group.world_size() == 1 {
        return Ok(());
    }
    // Two 24-bit halves: exact in f32.
    let halves = [(value >> 24) as f32, (value & 0xff_ffff) as f32];
    let mine = Tensor::<B, 1>::from_floats(halves, device);
    let first = group.broadcast(mine.clone(), 0)?;
    let spread = group.all_reduce_mean((mine - first.clone()).abs().sum())?;
    let spread = spread.into_data().iter::<f64>().next().unwrap_or(0.0);
    let rank0: Vec<f64> = first.into_data().iter::<f64>().collect();
    let rank0 = match rank0.as_slice() {
        [hi, lo] => ((*hi as u64) << 24) | *lo as u64,
        _ => value,
    };
    if spread > 0.0 {
        return Err(DistError::Disagree {
            rank: group.rank(),
            what: what.into(),
            value,
            rank0,
        });
    }
    Ok(())
}

/// Rank 0's decision to stop, on every rank (a time limit reads each rank's own clock, so ranks may
/// disagree on it). One rank's decision stands alone.
pub fn rank0_decides<B: Backend>(
    group: &mut dyn ProcessGroup<B>,
    stop: bool,
    device: &B::Device,
) -> Result<bool> {
    if group.world_size() == 1 {
        return Ok(stop);
    }
    let flag = Tensor::<B, 1>::from_floats([f32::from(u8::from(stop))], device);
    let first = group.broadcast(flag, 0)?.into_data();
    Ok(first.iter::<f64>().next().unwrap_or(0.0) > 0.5)
}

#[cfg(test)]
mod tests {
    use super::{buckets, buckets_of};

    #[test]
    fn buckets_cover_every_tensor_once() {
        assert_eq!(buckets(&[4, 4, 4, 10, 1], 8), vec![0..2, 2..4, 4..5]);
        assert_eq!(
            buckets_of(&[4, 4, 4, 10, 1], 8, 1),
            vec![0..1, 1..2, 2..3, 3..4, 4..5]
        );
        assert_eq!(buckets_of(&[1, 1, 1, 1, 9], 100, 2), vec![0..2, 2..4, 4..5]);
        assert_eq!(buckets(&[100], 8), vec![0..1]);
        assert_eq!(buckets(&[], 8), Vec::<std::ops::Range<usize>>::new());
        assert_eq!(buckets(&[1, 1, 1], 0), vec![0..1, 1..2, 2..3]);
    }
}
