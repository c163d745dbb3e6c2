"""Kernel families of a training step, for umgen's and PyTorch's kernels alike (docs/performance.md).

`gpu-time-step.sh` (umgen under Nsight Compute) and `torch-time-step.py` (the PyTorch reference under
torch.profiler) both sum a steady step's GPU time per kernel name; `family` puts each name in the same
families so that the two steps can be set side by side: where one spends more, by kind of work.
"""

import re

# First match wins: the specific names (umgen's own kernels, PyTorch's named kernels) before the
# generic element-wise ones.
RULES = [
    ("attention", r"flash|fmha|cudnn|sdpa|attention|umgen_flash2|flash_fwd|flash_bwd"),
    ("attention over time", r"umgen_temporal"),
    ("products", r"gemm|gemv|nvjet|xmma|cutlass|cublas|umgen_matmul|matmul"),
    ("layer norm", r"layer_norm|layernorm|umgen_norm"),
    ("bias + GELU", r"gelu"),
    ("cross-entropy", r"xent|cross_entropy|nll_loss|log_softmax|softmax"),
    ("optimizer", r"adam|multi_tensor_apply|umgen_adamw|foreach"),
    ("embedding", r"embedding|index_select|indexing_backward|umgen_lookup|scatter|gather"),
    ("reductions", r"reduce|sum|umgen_rows|column"),
    ("casts", r"cast|convert|copy"),
    ("fused element-wise", r"triton_|elementwise|elemwise|fused|vectorized|unrolled|kernel_"),
]
COMPILED = [(name, re.compile(pattern, re.IGNORECASE)) for name, pattern in RULES]


def family(kernel: str) -> str:
    """The family of a kernel's name (`other` when no rule matches)."""
    for name, pattern in COMPILED:
        if pattern.search(kernel):
            return name
    return "other"


def summary(by_kernel: dict, launches: dict, top: int = 25) -> str:
    """A step's GPU time by family and its largest kernels, as text."""
    total = sum(by_kernel.values())
    fam, n = {}, {}
    for k, ms in by_kernel.items():
        f = family(k)
        fam[f] = fam.get(f, 0.0) + ms
        n[f] = n.get(f, 0) + launches.get(k, 0)
    lines = [f"GPU time of a steady step: {total:.1f} ms in {sum(launches.values())} launches", "by family:"]
    for f, ms in sorted(fam.items(), key=lambda kv: -kv[1]):
        lines.append(f"{ms:9.2f} ms {100 * ms / total:5.1f} % {n[f]:6d} launches  {f}")
    lines.append("largest kernels:")
    for k, ms in sorted(by_kernel.items(), key=lambda kv: -kv[1])[:top]:
        lines.append(f"{ms:9.2f} ms {100 * ms / total:5.1f} % {launches.get(k, 0):6d} launches  [{family(k)}] {k[:90]}")
    return "\n".join(lines)
