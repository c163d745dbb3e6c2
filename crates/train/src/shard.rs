//! A run's optimizer state shared out among its ranks (`train.shard_optimizer`, ZeRO stage 1): each rank
//! keeps AdamW's moments for its share of the parameters ([`umgen_dist::Shards`]). Checkpoints still hold
//! the whole state in the unsharded format, gathered to rank 0 one parameter at a time (so no rank holds
//! it all on the device), and a run that resumes keeps only its share of what a checkpoint holds, however
//! that checkpoint was written.

use crate::error::{Result, TrainError};
use burn::module::{AutodiffModule, ModuleVisitor, Param, ParamId};
use burn::optim::record::AdaptorRecord;
use burn::optim::{AdamW, AdamWState, AdaptiveMomentumState, Optimizer};
use burn::record::{FullPrecisionSettings, Record};
use burn::tensor::Tensor;
use burn::tensor::backend::AutodiffBackend;
use std::collections::HashMap;
use umgen_checkpoint::burn_io::{RecordItem, optimizer_items_to_bytes, optimizer_records_from_bytes};
use umgen_dist::{ProcessGroup, Shards};
use umgen_optim::FusedAdamW;

/// One parameter's AdamW record, as the optimizer keeps it.
type Entry<B> = AdaptorRecord<AdamW, B>;

/// AdamW's step count travels as an f32 beside the moments: exact up to 2^24.
const MAX_TIME: usize = 1 << 24;

/// `optim` holding this rank's share of the optimizer state in `bytes` (written by a sharded run or not).
pub(crate) fn load_share<B: AutodiffBackend, M: AutodiffModule<B>>(
    optim: FusedAdamW<M, B>,
    bytes: &[u8],
    device: &B::Device,
    shards: &Shards,
) -> Result<FusedAdamW<M, B>> {
    let owned = shards.owned();
    let record = optimizer_records_from_bytes::<B, Entry<B>, _>(bytes, device, |id| owned.contains(&id))?;
    Ok(optim.load_record(record))
}

/// The whole optimizer state of a sharded run as checkpoint bytes, on rank 0 (`None` elsewhere). Every
/// rank must call it at the same step: each parameter's moments go from its owner to rank 0.
pub(crate) fn gathered_bytes<B: AutodiffBackend, M: AutodiffModule<B>>(
    optim: &FusedAdamW<M, B>,
    model: &M,
    shards: &Shards,
    group: &mut dyn ProcessGroup<B::InnerBackend>,
) -> Result<Option<Vec<u8>>> {
    let rank = group.rank();
    let mut gather = Gather::<B> {
        shards,
        rank,
        own: optim.to_record().into_iter().collect(),
        group,
        items: HashMap::new(),
        error: None,
    };
    model.visit(&mut gather);
    if let Some(e) = gather.error {
        return Err(e);
    }
    if rank != 0 {
        return Ok(None);
    }
    Ok(Some(optimizer_items_to_bytes::<B, Entry<B>>(gather.items)?))
}

/// Visits the parameters in module order (the same on every rank), moving each one's record to rank 0.
struct Gather<'a, B: AutodiffBackend> {
    shards: &'a Shards,
    rank: usize,
    /// This rank's records.
    own: HashMap<ParamId, Entry<B>>,
    group: &'a mut dyn ProcessGroup<B::InnerBackend>,
    /// Rank 0's items, in host memory.
    items: HashMap<ParamId, RecordItem<B, Entry<B>>>,
    error: Option<TrainError>,
}

impl<B: AutodiffBackend> ModuleVisitor<B> for Gather<'_, B> {
    fn visit_float<const D: usize>(&mut self, param: &Param<Tensor<B, D>>) {
        if self.error.is_none()
            && let Err(e) = self.one(param)
        {
            self.error = Some(e);
        }
    }
}

impl<B: AutodiffBackend> Gather<'_, B> {
    fn one<const D: usize>(&mut self, param: &Param<Tensor<B, D>>) -> Result<()> {
        let id = param.id;
        let owner = self.shards.owner(id).ok_or_else(|| {
            TrainError::Setup(format!("parameter {id} is in no shard of the optimizer state"))
        })?;
        let value = param.val().inner();
        let (shape, device) = (value.shape(), value.device());
        let n = shape.num_elements();
        // [first moment, second moment, step count]; a step count of 0 means no state yet.
        let packed = if self.rank == owner {
            match self.own.remove(&id) {
                Some(entry) => {
                    let state: AdamWState<B::InnerBackend, D> = entry.into_state();
                    let m = state.momentum;
                    if m.time >= MAX_TIME {
                        return Err(TrainError::Setup(format!(
                            "parameter {id} has taken {} AdamW steps: a sharded checkpoint carries at most {MAX_TIME}",
                            m.time
                        )));
                    }
                    let time = Tensor::from_floats([m.time as f32], &device);
                    Tensor::cat(vec![m.moment_1.reshape([n]), m.moment_2.reshape([n]), time], 0)
                }
                None => Tensor::zeros([2 * n + 1], &device),
            }
        } else {
            Tensor::zeros([2 * n + 1], &device)
        };
        // Rank 0 already has what it owns.
        let packed = match owner {
            0 => packed,
            _ => self.group.broadcast(packed, owner)?,
        };
        if self.rank != 0 {
            return Ok(());
        }
        let time = packed
            .clone()
            .slice(2 * n..2 * n + 1)
            .into_data()
            .iter::<f32>()
            .next()
            .unwrap_or(0.0) as usize;
        if time == 0 {
            return Ok(());
        }
        let moment = |k: usize| packed.clone().slice(k * n..(k + 1) * n).reshape(shape.clone());
        let state = AdamWState {
            momentum: AdaptiveMomentumState {
                time,
                moment_1: moment(0),
                moment_2: moment(1),
                max_moment_2: None,
            },
        };
        let item = Entry::<B>::from_state::<D>(state).into_item::<FullPrecisionSettings>();
        self.items.insert(id, item);
        Ok(())
    }
}
