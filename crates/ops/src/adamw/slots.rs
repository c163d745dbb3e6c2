//! What the AdamW and gradient-norm launches share: slot counts, block sizes, and the entry points over
//! slots of buffers (`adamw.cu` is compiled with both kernels' slot counts).

use crate::side;
use cubecl::server::Binding;

/// Parameter tensors a launch updates (`UMGEN_ADAMW_SLOTS`): seven pointers each, so that the launch's
/// parameters (1,800 bytes of pointers and the 684 bytes of `Params`) stay within CUDA's 4 KiB.
pub(super) const ADAMW_SLOTS: usize = 32;

/// Gradients a launch reads (`UMGEN_SUMSQ_SLOTS`).
pub(super) const SUMSQ_SLOTS: usize = 128;

/// Elements a block updates or reads (`UMGEN_ADAMW_SPAN`), in either kernel.
pub(super) const SPAN: usize = 4096;

/// Threads a block (`UMGEN_ADAMW_THREADS`), in either kernel.
pub(super) const THREADS: u32 = 256;

/// Repeats the first slot's `per_slot` buffers (after the `fixed` ones) until `buffers` holds `slots`
/// slots: a [`Slotted`] entry point takes every slot, and reads only the first `count`.
pub(super) fn fill_slots(buffers: &mut Vec<Binding>, fixed: usize, per_slot: usize, slots: usize) {
    let first: Vec<Binding> = buffers[fixed..fixed + per_slot].to_vec();
    while buffers.len() < fixed + per_slot * slots {
        buffers.extend(first.iter().cloned());
    }
}

/// An entry point over slots of buffers: it takes the `fixed` parameters, then `slots` groups of
/// `per_slot` pointers (named, and whether they are read only), then `params` by value; it finds its
/// block's slot `i` (`slot_of`), gathers that slot's pointers into a `slot_type` and runs `call`.
pub(super) struct Slotted<'a> {
    pub(super) entry: &'a str,
    pub(super) fixed: &'a str,
    pub(super) per_slot: &'a [(&'a str, bool)],
    pub(super) slots: usize,
    pub(super) params: &'a str,
    pub(super) slot_type: &'a str,
    pub(super) call: &'a str,
}

impl Slotted<'_> {
    /// `adamw.cu` (with its slot counts defined, after the warp primitives of `side::kernel_source`) and
    /// this entry point.
    pub(super) fn source(&self) -> String {
        let mut s = format!(
            "#define UMGEN_ADAMW_SLOTS {ADAMW_SLOTS}\n#define UMGEN_SUMSQ_SLOTS {SUMSQ_SLOTS}\n{}\n",
            side::kernel_source(umgen_cuda::source::train::ADAMW)
        );
        s.push_str(&format!(
            "extern \"C\" __global__ void __launch_bounds__(UMGEN_ADAMW_THREADS) {}({}",
            self.entry, self.fixed
        ));
        for i in 0..self.slots {
            for (name, read_only) in self.per_slot {
                let constness = if *read_only { "const " } else { "" };
                s.push_str(&format!(", {constness}float* {name}{i}"));
            }
        }
        s.push_str(&format!(
            ", {} p) {{\n    const unsigned int i = slot_of(p, blockIdx.x);\n    {} s;\n    switch (i) {{\n",
            self.params, self.slot_type
        ));
        for i in 0..self.slots {
            let fields: Vec<String> = self.per_slot.iter().map(|(n, _)| format!("{n}{i}")).collect();
            s.push_str(&format!(
                "    case {i}: s = {}{{{}}}; break;\n",
                self.slot_type,
                fields.join(", ")
            ));
        }
        s.push_str(&format!("    default: return;\n    }}\n    {};\n}}\n", self.call));
        s
    }
}
