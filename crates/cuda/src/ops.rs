//! The operations of the generation engine and the interface of what runs them.
//!
//! An operation names its buffers by [`Buf`] (an allocation of the executor and the element it starts
//! at) and carries its sizes and strides in elements, so that one program runs on any executor. Each
//! operation is one kernel of `src/kernels` (or one cuBLAS product) and says which elements of which
//! buffers it reaches ([`Op::accesses`]); executors check those before they run it.

mod accesses;
mod attention;
mod draw;
mod products;
mod rows;

pub use accesses::Access;
pub use attention::*;
pub use draw::*;
pub use products::*;
pub use rows::*;

/// The element type of a buffer.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Elem {
    /// f32.
    F32,
    /// The weights' and product operands' type: bf16 or f32, as the executor was made.
    W,
    /// i32 (tokens, positions, tables of indices).
    I32,
    /// u32 (counters).
    U32,
    /// Bytes (flags).
    U8,
    /// f64 (boxes).
    F64,
    /// [`Rule`]s.
    Rule,
    /// [`GroupRun`]s.
    Run,
}

/// A buffer of an executor from one of its elements on.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub struct Buf {
    /// The allocation.
    pub id: u32,
    /// The first element.
    pub at: usize,
}

impl Buf {
    /// The same buffer from `offset` elements further on.
    pub fn at(self, offset: usize) -> Self {
        Self {
            id: self.id,
            at: self.at + offset,
        }
    }
}

/// Host data written into a buffer.
#[derive(Debug, Clone, Copy)]
pub enum Data<'a> {
    /// Into an `F32` or a `W` buffer (rounded to bf16 where `W` is).
    F32(&'a [f32]),
    /// Into an `I32` buffer.
    I32(&'a [i32]),
    /// Into a `U32` buffer.
    U32(&'a [u32]),
    /// Into a `U8` buffer.
    U8(&'a [u8]),
    /// Into an `F64` buffer.
    F64(&'a [f64]),
    /// Into a `Rule` buffer.
    Rules(&'a [Rule]),
    /// Into a `Run` buffer.
    Runs(&'a [GroupRun]),
}

impl Data<'_> {
    /// Elements.
    pub fn len(&self) -> usize {
        match self {
            Self::F32(d) => d.len(),
            Self::I32(d) => d.len(),
            Self::U32(d) => d.len(),
            Self::U8(d) => d.len(),
            Self::F64(d) => d.len(),
            Self::Rules(d) => d.len(),
            Self::Runs(d) => d.len(),
        }
    }

    /// Whether there is nothing to write.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// The buffer types it may be written into.
    pub fn kinds(&self) -> &'static [Elem] {
        match self {
            Self::F32(_) => &[Elem::F32, Elem::W],
            Self::I32(_) => &[Elem::I32],
            Self::U32(_) => &[Elem::U32],
            Self::U8(_) => &[Elem::U8],
            Self::F64(_) => &[Elem::F64],
            Self::Rules(_) => &[Elem::Rule],
            Self::Runs(_) => &[Elem::Run],
        }
    }
}

/// Why an executor could not do what it was asked.
#[derive(Debug, thiserror::Error)]
pub enum ExecError {
    /// An operation reaches past the end of a buffer.
    #[error("{what} reaches element {end} of buffer {id}, which holds {len}")]
    Bounds {
        /// The operation and operand.
        what: String,
        /// The buffer.
        id: u32,
        /// One past the last element reached.
        end: usize,
        /// Elements the buffer holds.
        len: usize,
    },
    /// An operand is a buffer of another type.
    #[error("{what}: buffer {id} holds {found:?}, not {want:?}")]
    Kind {
        /// The operation and operand.
        what: String,
        /// The buffer.
        id: u32,
        /// Its type.
        found: Elem,
        /// The types the operand takes.
        want: Vec<Elem>,
    },
    /// No such buffer.
    #[error("{what}: no buffer {id}")]
    Missing {
        /// The operation and operand.
        what: String,
        /// The buffer named.
        id: u32,
    },
    /// Sizes the kernels cannot take.
    #[error("{0}")]
    Invalid(String),
    /// The device failed (CUDA, NVRTC or cuBLAS said why).
    #[error("device: {0}")]
    Device(String),
}

/// What runs the engine's operations: on the host, or on a GPU (`gpu::CudaExec`).
pub trait Exec {
    /// A new buffer of `len` elements of `elem`, zeroed.
    fn alloc(&mut self, elem: Elem, len: usize) -> Result<Buf, ExecError>;

    /// Frees buffer `id` (any later use of it is an error).
    fn free(&mut self, id: u32);

    /// Writes `data` from element `dst.at` on.
    fn write(&mut self, dst: Buf, data: Data<'_>) -> Result<(), ExecError>;

    /// `len` elements of an `F32` or `W` buffer from `src.at` on, in f32.
    fn read_f32(&mut self, src: Buf, len: usize) -> Result<Vec<f32>, ExecError>;

    /// `len` elements of an `I32` buffer from `src.at` on.
    fn read_i32(&mut self, src: Buf, len: usize) -> Result<Vec<i32>, ExecError>;

    /// `len` elements of a `U32` buffer from `src.at` on.
    fn read_u32(&mut self, src: Buf, len: usize) -> Result<Vec<u32>, ExecError>;

    /// Runs one operation (queued, on a GPU: it has run once a read returns).
    fn run(&mut self, op: &Op) -> Result<(), ExecError>;

    /// Runs `ops` in order. A GPU executor captures them as a graph under `key` the first time and replays
    /// that graph afterwards, so the buffers they name must stay the same (see [`Exec::forget_replays`]).
    fn replay(&mut self, key: u64, ops: &[Op]) -> Result<(), ExecError> {
        let _ = key;
        ops.iter().try_for_each(|op| self.run(op))
    }

    /// Forgets every captured sequence (after the buffers they name changed).
    fn forget_replays(&mut self) {}

    /// Waits until everything queued has run (for timing; reads wait by themselves).
    fn sync(&mut self) -> Result<(), ExecError> {
        Ok(())
    }

    /// Bytes of device memory its buffers hold.
    fn bytes(&self) -> usize;

    /// Whether `W` buffers hold bf16.
    fn bf16(&self) -> bool;

    /// Whether it runs [`Op::Flash`] for head size `dh` (the flash2 kernels: bf16 operands, head sizes 32
    /// and 64, a GPU of compute capability 8.0 or newer).
    fn flash(&self, dh: usize) -> bool {
        let _ = dh;
        false
    }
}

/// One operation.
#[derive(Debug, Clone)]
pub enum Op {
    /// A matrix-vector product of up to [`GEMV_ROWS`] rows with its prologue and epilogue.
    Gemv(Gemv),
    /// A product of many rows (cuBLAS on a GPU).
    Gemm(Gemm),
    /// Few queries over many keys.
    AttendRows(AttendRows),
    /// Many queries, tiles of keys.
    AttendTiles(AttendTiles),
    /// FlashAttention-2's forward pass.
    Flash(Flash),
    /// Gathered, normalised, biased rows into f32 or `W` rows.
    Rows(Rows),
    /// Bias and GELU in place on `W` rows.
    BiasT(BiasT),
    /// Embedding inputs of tokens.
    Embed(Embed),
    /// The action block shifted one frame back.
    Shift(Shift),
    /// AMA.
    Align(Align),
    /// The tracked slots moved ahead.
    Track(Track),
    /// The decoding step's draw.
    Draw(Draw),
}

impl Op {
    /// The kernel's (or cuBLAS's) name, for errors.
    pub fn name(&self) -> &'static str {
        match self {
            Self::Gemv(_) => "umgen_gemv",
            Self::Gemm(_) => "cublasGemmEx",
            Self::AttendRows(_) => "umgen_attend_rows",
            Self::AttendTiles(_) => "umgen_attend_tiles",
            Self::Flash(_) => "umgen_flash2_forward",
            Self::Rows(_) => "umgen_rows",
            Self::BiasT(_) => "umgen_bias_t",
            Self::Embed(_) => "umgen_embed",
            Self::Shift(_) => "umgen_shift_block",
            Self::Align(_) => "umgen_align",
            Self::Track(_) => "umgen_track",
            Self::Draw(_) => "umgen_draw",
        }
    }
}

/// Checks an operation's accesses against the buffers' types and lengths, as `info(id)` gives them.
pub fn check(op: &Op, info: impl Fn(u32) -> Option<(Elem, usize)>) -> Result<(), ExecError> {
    op.validate()?;
    for a in op.accesses() {
        let what = || format!("{} ({})", op.name(), a.what);
        let (elem, len) = info(a.buf.id).ok_or_else(|| ExecError::Missing {
            what: what(),
            id: a.buf.id,
        })?;
        if !a.kinds.contains(&elem) {
            return Err(ExecError::Kind {
                what: what(),
                id: a.buf.id,
                found: elem,
                want: a.kinds.to_vec(),
            });
        }
        let end = a.buf.at + a.end;
        if end > len {
            return Err(ExecError::Bounds {
                what: what(),
                id: a.buf.id,
                end,
                len,
            });
        }
    }
    Ok(())
}
