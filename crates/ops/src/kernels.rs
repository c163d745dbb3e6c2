//! The kernel choices of a run ([`Kernels`], `[train.kernels]` in configs): one value that the model hands
//! to every operation it calls, and that each operation's backward pass keeps with what it saved.
//!
//! A choice changes how an operation is computed (which kernel, on which stream, from which thread, how
//! much it keeps for the backward pass), never what it computes: two runs that differ only in these agree
//! within the kernels' rounding. The CPU ignores every choice but `recompute`, `layer`, `recompute_gelu` (in a layer run as one
//! operation) and `attention_block_mib` (its tiled attention's blocks); CUDA reads them all.

use serde::{Deserialize, Serialize};

mod choices;
mod side_sync;
pub use choices::{
    AdamWChoice, AttentionKernel, EpilogueKernel, Flash2Backward, GeluKernel, KeptInputs, KernelStream,
    LaunchThread, LayerKernel, MatmulKernel, NormKernel, XentKernel,
};
pub use side_sync::{SideFamily, SideSync};

/// Keys (or queries, for the key/value gradients) per step of a fused kernel's loop that the kernels
/// take: multiples of 16 up to [`crate::flash::BLOCK`].
pub const STEPS: [usize; 3] = [16, 32, 64];

/// The step the kernels use unless told otherwise (`train.kernels.attention_step`).
pub const DEFAULT_STEP: usize = 16;

/// Bytes one block's score matrix may take by default; sets the query block length. Few, large blocks:
/// every causal block has its own key length, hence its own kernel shapes to compile and tune on CUDA.
pub const BLOCK_BYTES: usize = 1 << 30;

/// Every kernel choice of a run. The defaults are the fastest measured on an H100 and an H200
/// (docs/performance.md).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct Kernels {
    /// Kernel of the linear layers' products on CUDA: `cublas` (cuBLAS, falling back to `named` where it
    /// is missing), `named` (cubek's `specialized_tma_mma`) or `burn` (burn's default kernel).
    pub matmul: MatmulKernel,
    /// Kernels of the training attention on CUDA: `flash2` (FlashAttention-2 in CUDA C, head sizes 32 and
    /// 64; others run `fused`), `fused` (one cubecl kernel per pass) or `tiled` (the tiled passes in burn
    /// tensor operations, in blocks of `attention_block_mib`).
    pub attention: AttentionKernel,
    /// Keys (or queries) per step of the fused attention kernels' loop, 16, 32 or 64: shorter steps take
    /// less shared memory per cube, so more cubes share an SM, for more loop steps and synchronisations.
    pub attention_step: usize,
    /// MiB one query block's attention scores may take in the tiled attention: smaller blocks skip more of
    /// a causal matrix's hidden half and launch more, smaller kernels.
    pub attention_block_mib: usize,
    /// Recompute each self-attention layer's activations in the backward pass instead of keeping them
    /// (activation checkpointing, [`crate::layer`]): the step keeps one activation per layer instead
    /// of about twenty, for one more forward pass of those layers. Every layer then runs as one
    /// operation, whatever `layer` says.
    pub recompute: bool,
    /// How a training backend runs the attention layers whose activations it keeps, [`LayerKernel`].
    pub layer: LayerKernel,
    /// The format the backward pass keeps the residual stream in where a layer norm is its only reader
    /// there (the inputs of recomputed layers, and of layer norms whose output feeds products): `operand`
    /// (the products' format, bf16 under the bf16 presets: half the memory of the f32 stream) or `f32`
    /// (the stream's own, so that the backward pass reads exactly what the forward pass did).
    pub kept_inputs: KeptInputs,
    /// What computes the layer norms on CUDA: `fused` (one CUDA C kernel per pass) or `burn` (burn's
    /// decomposition).
    pub norm: NormKernel,
    /// Recompute each MLP's activation `gelu(x · W + b)` in the second product's backward pass from the
    /// first product's output, which the bias + GELU keeps anyway, instead of keeping it (with `gelu =
    /// "fused"` and the named products; [`crate::mlp`]): one `[rows, 4d]` tensor less per MLP for
    /// one more bias + GELU pass. The gradients are the same bit for bit.
    pub recompute_gelu: bool,
    /// What computes the MLPs' bias + GELU: `fused` (one operation per pass writing the activation in the
    /// next product's format; on CUDA one CUDA C kernel) or `burn` (burn's bias add and GELU in f32).
    pub gelu: GeluKernel,
    /// What computes the cross-entropy's passes over the logits on CUDA: `fused` (one CUDA C kernel per
    /// pass) or `burn` (burn's operations).
    pub xent: XentKernel,
    /// What steps AdamW on CUDA: `fused` (one CUDA C kernel over all parameter tensors, the clipping factor
    /// applied as it reads the gradients) or `burn` (burn's AdamW, tensor by tensor).
    pub adamw: AdamWChoice,
    /// Where the CUDA C kernels and cuBLAS's products run: `cubecl` (cubecl's own stream, launched as
    /// cubecl kernels) or `side` (a side stream per kernel family, ordered with cubecl's through device
    /// flags).
    pub stream: KernelStream,
    /// Which thread launches the custom operations' kernels and cuBLAS products on CUDA: `device`
    /// (cubecl's device thread, one blocking call per operation) or `caller` (the training thread, one
    /// blocking call to cubecl's device thread per device pointer).
    pub launch_thread: LaunchThread,
    /// Warps per block of the flash2 kernels, 4 or 8 (each warp owns 16 query rows).
    pub flash2_warps: usize,
    /// How the flash2 kernels compute the backward pass, [`Flash2Backward`].
    pub attention_backward: Flash2Backward,
    /// Where the host waits around side-stream work (`stream = "side"` only), [`SideSync`].
    pub side_sync: SideSync,
    /// How the additions around the products and layer norms run, [`EpilogueKernel`].
    pub epilogue: EpilogueKernel,
}

impl Default for Kernels {
    fn default() -> Self {
        Self::DEFAULT
    }
}

impl Kernels {
    /// The defaults (each enum's own default, which a test checks).
    pub const DEFAULT: Self = Self {
        matmul: MatmulKernel::Cublas,
        attention: AttentionKernel::Flash2,
        attention_step: DEFAULT_STEP,
        attention_block_mib: BLOCK_BYTES >> 20,
        recompute: false,
        layer: LayerKernel::Burn,
        kept_inputs: KeptInputs::Operand,
        norm: NormKernel::Fused,
        recompute_gelu: true,
        gelu: GeluKernel::Fused,
        xent: XentKernel::Fused,
        adamw: AdamWChoice::Fused,
        stream: KernelStream::Cubecl,
        launch_thread: LaunchThread::Device,
        flash2_warps: 8,
        attention_backward: Flash2Backward::TwoPass,
        side_sync: SideSync::DEFAULT,
        epilogue: EpilogueKernel::Fused,
    };

    /// The first choice no run can use, as (key under `[train.kernels]`, what is wrong with its value).
    pub fn problem(&self) -> Option<(&'static str, String)> {
        if self.attention_block_mib == 0 {
            return Some((
                "attention_block_mib",
                "0: a query block needs at least 1 MiB of scores".into(),
            ));
        }
        if !matches!(self.flash2_warps, 4 | 8) {
            return Some((
                "flash2_warps",
                format!(
                    "{}: the flash2 kernels take 4 or 8 warps a block",
                    self.flash2_warps
                ),
            ));
        }
        if self.attention_backward == Flash2Backward::OnePass && self.stream != KernelStream::Cubecl {
            return Some((
                "attention_backward",
                "\"one-pass\" runs on cubecl's stream only (train.kernels.stream = \"cubecl\")".into(),
            ));
        }
        check_step(self.attention_step)
            .err()
            .map(|e| ("attention_step", e))
    }

    /// Bytes one query block's scores may take in the tiled attention.
    pub fn block_bytes(&self) -> usize {
        self.attention_block_mib.max(1) << 20
    }
}

/// `step` if the fused kernels take it (one of [`STEPS`]); the error names it and the steps they take.
pub fn check_step(step: usize) -> Result<usize, String> {
    if STEPS.contains(&step) {
        Ok(step)
    } else {
        Err(format!(
            "attention step {step}: the fused kernels take {STEPS:?} rows per step"
        ))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_table_parses_with_defaults_for_what_it_leaves_out_and_refuses_unknown_keys() {
        let k: Kernels = serde_json::from_str(r#"{"matmul": "named", "stream": "side", "recompute": true}"#)
            .expect("a partial table parses");
        let expected = Kernels {
            matmul: MatmulKernel::Named,
            stream: KernelStream::Side,
            recompute: true,
            ..Kernels::default()
        };
        assert_eq!(k, expected);
        assert_eq!(Kernels::default().attention_step, 16);
        assert_eq!(Kernels::default().block_bytes(), 1 << 30);
        let e = serde_json::from_str::<Kernels>(r#"{"kernel_stream": "side"}"#).expect_err("unknown key");
        assert!(e.to_string().contains("kernel_stream"), "{e}");
        let parsed: Vec<KernelStream> = serde_json::from_str(r#"["cubecl", "side"]"#).expect("both names");
        assert_eq!(parsed, [KernelStream::Cubecl, KernelStream::Side]);
        let parsed: Vec<LaunchThread> = serde_json::from_str(r#"["device", "caller"]"#).expect("both names");
        assert_eq!(parsed, [LaunchThread::Device, LaunchThread::Caller]);
        assert!(serde_json::from_str::<AttentionKernel>(r#""flash3""#).is_err());
        let parsed: Vec<Flash2Backward> =
            serde_json::from_str(r#"["two-pass", "one-pass"]"#).expect("both names");
        assert_eq!(parsed, [Flash2Backward::TwoPass, Flash2Backward::OnePass]);
        assert!(serde_json::from_str::<Flash2Backward>(r#""one_pass""#).is_err());
        let parsed: Vec<EpilogueKernel> = serde_json::from_str(r#"["fused", "apart"]"#).expect("both names");
        assert_eq!(parsed, [EpilogueKernel::Fused, EpilogueKernel::Apart]);
        let parsed: Vec<LayerKernel> = serde_json::from_str(r#"["burn", "fused"]"#).expect("both names");
        assert_eq!(parsed, [LayerKernel::Burn, LayerKernel::Fused]);
    }

    #[test]
    fn the_defaults_are_each_choices_own() {
        let d = Kernels::DEFAULT;
        assert_eq!(
            (
                d.matmul,
                d.attention,
                d.norm,
                d.gelu,
                d.xent,
                d.adamw,
                d.stream,
                d.launch_thread,
                d.kept_inputs,
                d.attention_backward,
                d.epilogue,
                d.layer
            ),
            (
                MatmulKernel::default(),
                AttentionKernel::default(),
                NormKernel::default(),
                GeluKernel::default(),
                XentKernel::default(),
                AdamWChoice::default(),
                KernelStream::default(),
                LaunchThread::default(),
                KeptInputs::default(),
                Flash2Backward::default(),
                EpilogueKernel::default(),
                LayerKernel::default()
            )
        );
    }

    #[test]
    fn unusable_choices_are_named() {
        let warps = Kernels {
            flash2_warps: 6,
            ..Kernels::default()
        };
        assert_eq!(warps.problem().map(|(k, _)| k), Some("flash2_warps"));
        let step = Kernels {
            attention_step: 48,
            ..Kernels::default()
        };
        let (key, why) = step.problem().expect("48 is not a step the kernels take");
        assert_eq!(key, "attention_step");
        assert!(why.contains("48") && why.contains("[16, 32, 64]"), "{why}");
        let block = Kernels {
            attention_block_mib: 0,
            ..Kernels::default()
        };
        assert_eq!(block.problem().map(|(k, _)| k), Some("attention_block_mib"));
        let one_pass_on_side = Kernels {
            attention_backward: Flash2Backward::OnePass,
            stream: KernelStream::Side,
            ..Kernels::default()
        };
        let (key, why) = one_pass_on_side
            .problem()
            .expect("one-pass needs cubecl's stream");
        assert_eq!(key, "attention_backward");
        assert!(why.contains("one-pass") && why.contains("cubecl"), "{why}");
        let one_pass = Kernels {
            attention_backward: Flash2Backward::OnePass,
            ..Kernels::default()
        };
        assert_eq!(one_pass.problem(), None);
        assert_eq!(Kernels::default().problem(), None);
    }
}
