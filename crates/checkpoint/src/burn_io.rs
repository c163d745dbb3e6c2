//! Burn modules and optimizers to and from bytes.
//!
//! Weights are safetensors whose tensor names are module paths (`encoder.conv_in.weight`), readable by
//! Python's `safetensors`. Optimizer state is burn's binary record, keyed by parameter ids; modules get
//! ids derived from their paths ([`stable_param_ids`]) so that state saved by one process matches the
//! parameters another process builds.

use crate::error::{CheckpointError, Result};
use burn::module::{AutodiffModule, Module, ModuleMapper, Param, ParamId};
use burn::optim::Optimizer;
use burn::record::{BinBytesRecorder, BurnRecord, FullPrecisionSettings, Record};
use burn::tensor::Tensor;
use burn::tensor::backend::{AutodiffBackend, Backend};
use burn::tensor::{DType, TensorData};
use burn_store::{ModuleSnapshot, SafetensorsStore};
use safetensors::{Dtype, tensor::TensorView};
use std::collections::HashMap;

/// FNV-1a: stable across runs, platforms and Rust versions.
fn fnv1a(s: &str) -> u64 {
    s.bytes().fold(0xcbf2_9ce4_8422_2325u64, |h, b| {
        (h ^ u64::from(b)).wrapping_mul(0x0100_0000_01b3)
    })
}

struct PathIds {
    path: Vec<String>,
}

impl PathIds {
    fn id(&self) -> ParamId {
        ParamId::from(fnv1a(&self.path.join(".")))
    }
}

impl<B: Backend> ModuleMapper<B> for PathIds {
    fn enter_module(&mut self, name: &str, _container: &str) {
        self.path.push(name.into());
    }

    fn exit_module(&mut self, _name: &str, _container: &str) {
        self.path.pop();
    }

    fn map_float<const D: usize>(&mut self, param: Param<Tensor<B, D>>) -> Param<Tensor<B, D>> {
        let (_, tensor, mapper) = param.consume();
        Param::from_mapped_value(self.id(), tensor, mapper)
    }

    fn map_int<const D: usize>(
        &mut self,
        param: Param<Tensor<B, D, burn::tensor::Int>>,
    ) -> Param<Tensor<B, D, burn::tensor::Int>> {
        let (_, tensor, mapper) = param.consume();
        Param::from_mapped_value(self.id(), tensor, mapper)
    }

    fn map_bool<const D: usize>(
        &mut self,
        param: Param<Tensor<B, D, burn::tensor::Bool>>,
    ) -> Param<Tensor<B, D, burn::tensor::Bool>> {
        let (_, tensor, mapper) = param.consume();
        Param::from_mapped_value(self.id(), tensor, mapper)
    }
}

/// The module with every parameter's id replaced by a hash of its path.
pub fn stable_param_ids<B: Backend, M: Module<B>>(module: M) -> M {
    module.map(&mut PathIds { path: Vec::new() })
}

fn safetensors_dtype(d: DType) -> Option<Dtype> {
    Some(match d {
        DType::F64 => Dtype::F64,
        DType::F32 | DType::Flex32 => Dtype::F32,
        DType::F16 => Dtype::F16,
        DType::BF16 => Dtype::BF16,
        DType::I64 => Dtype::I64,
        DType::I32 => Dtype::I32,
        DType::I16 => Dtype::I16,
        DType::I8 => Dtype::I8,
        DType::U64 => Dtype::U64,
        DType::U32 => Dtype::U32,
        DType::U16 => Dtype::U16,
        DType::U8 => Dtype::U8,
        DType::Bool(_) => Dtype::BOOL,
        _ => return None,
    })
}

/// The module's weights as safetensors bytes, named by module path. The bytes depend only on the
/// weights: tensors are sorted by name and no metadata map is written (burn-store's writer orders its
/// metadata by hash, so equal weights would give different files and checksums).
pub fn weights_to_bytes<B: Backend, M: Module<B>>(module: &M) -> Result<Vec<u8>> {
    let fail = |reason: String| CheckpointError::Weights {
        what: "weights".into(),
        reason,
    };
    let mut tensors: Vec<(String, TensorData)> = module
        .collect(None, None, false)
        .into_iter()
        .map(|s| {
            s.to_data()
                .map(|d| (s.full_path(), d))
                .map_err(|e| fail(format!("{}: {e:?}", s.full_path())))
        })
        .collect::<Result<_>>()?;
    tensors.sort_by(|a, b| a.0.cmp(&b.0));
    let views = tensors
        .iter()
        .map(|(name, d)| {
            let dtype = safetensors_dtype(d.dtype)
                .ok_or_else(|| fail(format!("{name}: dtype {:?} has no safetensors code", d.dtype)))?;
            TensorView::new(dtype, d.shape.to_vec(), d.as_bytes())
                .map(|v| (name.clone(), v))
                .map_err(|e| fail(format!("{name}: {e}")))
        })
        .collect::<Result<Vec<_>>>()?;
    safetensors::serialize(views, None).map_err(|e| fail(e.to_string()))
}

/// The name of the first tensor (by name) of safetensors `bytes` that holds a NaN or an infinity, among
/// its f32, f16 and bf16 tensors; `None` when every value is finite. Checkpoints and bundles are checked
/// with it before they are written or used.
pub fn first_non_finite(bytes: &[u8]) -> Result<Option<String>> {
    let st = safetensors::SafeTensors::deserialize(bytes).map_err(|e| CheckpointError::Weights {
        what: "weights".into(),
        reason: e.to_string(),
    })?;
    let mut names: Vec<String> = st.names().into_iter().map(str::to_string).collect();
    names.sort();
    for name in names {
        let Ok(view) = st.tensor(&name) else { continue };
        let data = view.data();
        let finite = match view.dtype() {
            Dtype::F32 => data
                .chunks_exact(4)
                .all(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]]).is_finite()),
            // Both keep an exponent of all ones for NaN and infinity.
            Dtype::BF16 => data
                .chunks_exact(2)
                .all(|b| u16::from_le_bytes([b[0], b[1]]) & 0x7f80 != 0x7f80),
            Dtype::F16 => data
                .chunks_exact(2)
                .all(|b| u16::from_le_bytes([b[0], b[1]]) & 0x7c00 != 0x7c00),
            _ => true,
        };
        if !finite {
            return Ok(Some(name));
        }
    }
    Ok(None)
}

/// Loads safetensors bytes into a module. Every tensor of the module must be present with its shape, and
/// every tensor of the file must be used; `what` names the weights in errors.
pub fn weights_from_bytes<B: Backend, M: Module<B>>(mut module: M, bytes: Vec<u8>, what: &str) -> Result<M> {
    let fail = |reason: String| CheckpointError::Weights {
        what: what.into(),
        reason,
    };
    let mut store = SafetensorsStore::from_bytes(Some(bytes));
    let r = module.load_from(&mut store).map_err(|e| fail(e.to_string()))?;
    if !r.errors.is_empty() {
        return Err(fail(format!(
            "{} tensors do not fit: {:?}",
            r.errors.len(),
            r.errors.iter().take(3).collect::<Vec<_>>()
        )));
    }
    if !r.missing.is_empty() {
        let names: Vec<&str> = r.missing.iter().take(5).map(|(p, _)| p.as_str()).collect();
        return Err(fail(format!(
            "{} tensors missing, e.g. {}",
            r.missing.len(),
            names.join(", ")
        )));
    }
    if !r.unused.is_empty() {
        return Err(fail(format!(
            "{} tensors the model does not have, e.g. {}",
            r.unused.len(),
            r.unused.iter().take(5).cloned().collect::<Vec<_>>().join(", ")
        )));
    }
    Ok(module)
}

/// An optimizer's state as bytes.
pub fn optimizer_to_bytes<B, M, O>(optim: &O) -> Result<Vec<u8>>
where
    B: AutodiffBackend,
    M: AutodiffModule<B>,
    O: Optimizer<M, B>,
{
    encode::<B, _>(optim.to_record().into_item::<FullPrecisionSettings>())
}

/// Restores an optimizer's state from bytes.
pub fn optimizer_from_bytes<B, M, O>(optim: O, bytes: Vec<u8>, device: &B::Device) -> Result<O>
where
    B: AutodiffBackend,
    M: AutodiffModule<B>,
    O: Optimizer<M, B>,
{
    let record: BurnRecord<RecordItem<B, O::Record>, B> = decode(&bytes)?;
    Ok(optim.load_record(O::Record::from_item(record.item, device)))
}

/// `item` as the bytes of a burn binary record, as `BinBytesRecorder` writes them but with an error, not
/// a panic, should encoding fail.
fn encode<B: Backend, I: serde::Serialize>(item: I) -> Result<Vec<u8>> {
    let record = BurnRecord::<_, B>::new::<BinBytesRecorder<FullPrecisionSettings>>(item);
    bincode::serde::encode_to_vec(record, bincode::config::standard()).map_err(|e| CheckpointError::Weights {
        what: "optimizer state".into(),
        reason: e.to_string(),
    })
}

/// A burn binary record from `bytes`, as `BinBytesRecorder` reads them but with an error, not a panic,
/// for bytes that are not one.
fn decode<I: serde::de::DeserializeOwned>(bytes: &[u8]) -> Result<I> {
    bincode::serde::decode_from_slice(bytes, bincode::config::standard())
        .map(|(item, _)| item)
        .map_err(|e| CheckpointError::Weights {
            what: "optimizer state".into(),
            reason: format!("not a burn binary record of this optimizer: {e}"),
        })
}

/// What the bytes hold of a record `T` (its item, in host memory).
pub type RecordItem<B, T> = <T as Record<B>>::Item<FullPrecisionSettings>;

/// The bytes [`optimizer_to_bytes`] writes for a record keyed by parameter id (as burn's optimizers keep
/// theirs), from its entries already turned into items: a sharded optimizer's state, gathered one
/// parameter at a time, need never be on one device whole.
pub fn optimizer_items_to_bytes<B: Backend, T: Record<B>>(
    items: impl IntoIterator<Item = (ParamId, RecordItem<B, T>)>,
) -> Result<Vec<u8>> {
    let keyed: HashMap<String, RecordItem<B, T>> = items
        .into_iter()
        .map(|(id, item)| (id.serialize(), item))
        .collect();
    encode::<B, _>(keyed)
}

/// The entries of the parameters that `keep` accepts, from bytes [`optimizer_to_bytes`] wrote (whether
/// or not the optimizer that wrote them was sharded), collected into the optimizer's record type; the
/// others never reach the device.
pub fn optimizer_records_from_bytes<B: Backend, T: Record<B>, R: FromIterator<(ParamId, T)>>(
    bytes: &[u8],
    device: &B::Device,
    keep: impl Fn(ParamId) -> bool,
) -> Result<R> {
    let record: BurnRecord<HashMap<String, RecordItem<B, T>>, B> = decode(bytes)?;
    Ok(record
        .item
        .into_iter()
        .map(|(key, item)| (ParamId::deserialize(&key), item))
        .filter(|(id, _)| keep(*id))
        .map(|(id, item)| (id, T::from_item(item, device)))
        .collect())
}

#[cfg(test)]
#[path = "burn_io_tests.rs"]
mod tests;
