//! [`HostExec`]: the engine's operations on the CPU, in f32, one loop per kernel of `umgen_cuda`'s
//! `src/kernels` (`host_ops.rs`, `host_draw.rs`): what the CPU tests run the engine with, and the
//! reference a GPU run is compared against.

use umgen_cuda::ops::{Buf, Data, Elem, Exec, ExecError, GroupRun, Op, Rule, check};

/// One buffer's elements.
#[derive(Debug, Clone)]
pub(super) enum Store {
    F32(Vec<f32>),
    I32(Vec<i32>),
    U32(Vec<u32>),
    U8(Vec<u8>),
    F64(Vec<f64>),
    Rules(Vec<Rule>),
    Runs(Vec<GroupRun>),
}

impl Store {
    fn len(&self) -> usize {
        match self {
            Self::F32(v) => v.len(),
            Self::I32(v) => v.len(),
            Self::U32(v) => v.len(),
            Self::U8(v) => v.len(),
            Self::F64(v) => v.len(),
            Self::Rules(v) => v.len(),
            Self::Runs(v) => v.len(),
        }
    }
}

/// The engine's operations on the host.
#[derive(Debug, Default)]
pub struct HostExec {
    pub(super) bufs: Vec<(Elem, Store)>,
    bytes: usize,
}

impl HostExec {
    /// An executor with no buffers.
    pub fn new() -> Self {
        Self::default()
    }

    fn info(&self, id: u32) -> Option<(Elem, usize)> {
        self.bufs.get(id as usize).map(|(e, s)| (*e, s.len()))
    }

    /// The f32 elements of buffer `b` from `b.at` on (an `F32` or `W` buffer, checked by the caller).
    pub(super) fn f32s(&self, b: Buf) -> &[f32] {
        match self.bufs.get(b.id as usize) {
            Some((_, Store::F32(v))) => &v[b.at.min(v.len())..],
            _ => &[],
        }
    }

    /// The i32 elements of buffer `b` from `b.at` on.
    pub(super) fn i32s(&self, b: Buf) -> &[i32] {
        match self.bufs.get(b.id as usize) {
            Some((_, Store::I32(v))) => &v[b.at.min(v.len())..],
            _ => &[],
        }
    }

    /// Buffer `b`'s f32 elements, to change.
    pub(super) fn f32s_mut(&mut self, b: Buf) -> &mut [f32] {
        match self.bufs.get_mut(b.id as usize) {
            Some((_, Store::F32(v))) => {
                let at = b.at.min(v.len());
                &mut v[at..]
            }
            _ => &mut [],
        }
    }

    /// Buffer `b`'s store, to take out while an operation writes it and reads others (put back by
    /// [`HostExec::put`]).
    pub(super) fn take(&mut self, id: u32) -> Store {
        match self.bufs.get_mut(id as usize) {
            Some((_, s)) => std::mem::replace(s, Store::U8(Vec::new())),
            None => Store::U8(Vec::new()),
        }
    }

    /// Puts back a store [`HostExec::take`] took.
    pub(super) fn put(&mut self, id: u32, store: Store) {
        if let Some((_, s)) = self.bufs.get_mut(id as usize) {
            *s = store;
        }
    }
}

impl Exec for HostExec {
    fn alloc(&mut self, elem: Elem, len: usize) -> Result<Buf, ExecError> {
        let store = match elem {
            Elem::F32 | Elem::W => Store::F32(vec![0.0; len]),
            Elem::I32 => Store::I32(vec![0; len]),
            Elem::U32 => Store::U32(vec![0; len]),
            Elem::U8 => Store::U8(vec![0; len]),
            Elem::F64 => Store::F64(vec![0.0; len]),
            Elem::Rule => Store::Rules(vec![Rule::FREE; len]),
            Elem::Run => Store::Runs(vec![GroupRun::EMPTY; len]),
        };
        let id = u32::try_from(self.bufs.len()).map_err(|_| ExecError::Invalid("too many buffers".into()))?;
        self.bytes += len * 4;
        self.bufs.push((elem, store));
        Ok(Buf { id, at: 0 })
    }

    fn free(&mut self, id: u32) {
        if let Some((_, s)) = self.bufs.get_mut(id as usize) {
            self.bytes = self.bytes.saturating_sub(s.len() * 4);
            *s = Store::U8(Vec::new());
        }
    }

    fn write(&mut self, dst: Buf, data: Data<'_>) -> Result<(), ExecError> {
        let (elem, len) = self.info(dst.id).ok_or(ExecError::Missing {
            what: "write".into(),
            id: dst.id,
        })?;
        if !data.kinds().contains(&elem) {
            return Err(ExecError::Kind {
                what: "write".into(),
                id: dst.id,
                found: elem,
                want: data.kinds().to_vec(),
            });
        }
        let end = dst.at + data.len();
        if end > len {
            return Err(ExecError::Bounds {
                what: "write".into(),
                id: dst.id,
                end,
                len,
            });
        }
        let range = dst.at..end;
        match (self.bufs.get_mut(dst.id as usize).map(|(_, s)| s), data) {
            (Some(Store::F32(v)), Data::F32(d)) => v[range].copy_from_slice(d),
            (Some(Store::I32(v)), Data::I32(d)) => v[range].copy_from_slice(d),
            (Some(Store::U32(v)), Data::U32(d)) => v[range].copy_from_slice(d),
            (Some(Store::U8(v)), Data::U8(d)) => v[range].copy_from_slice(d),
            (Some(Store::F64(v)), Data::F64(d)) => v[range].copy_from_slice(d),
            (Some(Store::Rules(v)), Data::Rules(d)) => v[range].copy_from_slice(d),
            (Some(Store::Runs(v)), Data::Runs(d)) => v[range].copy_from_slice(d),
            _ => {
                return Err(ExecError::Invalid(
                    "write: the data does not match the buffer".into(),
                ));
            }
        }
        Ok(())
    }

    fn read_f32(&mut self, src: Buf, len: usize) -> Result<Vec<f32>, ExecError> {
        match self.bufs.get(src.id as usize) {
            Some((_, Store::F32(v))) if src.at + len <= v.len() => Ok(v[src.at..src.at + len].to_vec()),
            _ => Err(ExecError::Invalid(format!(
                "read of {len} f32 from buffer {}",
                src.id
            ))),
        }
    }

    fn read_i32(&mut self, src: Buf, len: usize) -> Result<Vec<i32>, ExecError> {
        match self.bufs.get(src.id as usize) {
            Some((_, Store::I32(v))) if src.at + len <= v.len() => Ok(v[src.at..src.at + len].to_vec()),
            _ => Err(ExecError::Invalid(format!(
                "read of {len} i32 from buffer {}",
                src.id
            ))),
        }
    }

    fn read_u32(&mut self, src: Buf, len: usize) -> Result<Vec<u32>, ExecError> {
        match self.bufs.get(src.id as usize) {
            Some((_, Store::U32(v))) if src.at + len <= v.len() => Ok(v[src.at..src.at + len].to_vec()),
            _ => Err(ExecError::Invalid(format!(
                "read of {len} u32 from buffer {}",
                src.id
            ))),
        }
    }

    fn run(&mut self, op: &Op) -> Result<(), ExecError> {
        check(op, |id| self.info(id))?;
        super::host_ops::run(self, op)
    }

    fn bytes(&self) -> usize {
        self.bytes
    }

    fn bf16(&self) -> bool {
        false
    }
}
