"""Parity with umgen: ``python -m umgen_torch.check BUNDLE`` computes the logits of the bundle's golden
file (``umgen export --golden N``) and prints, per head, the largest absolute difference from umgen's and
that difference relative to the largest umgen logit. Exits 1 when a head is past the tolerances."""

import argparse
import sys

import torch
from safetensors import safe_open

from .bundle import Bundle, BundleError, load


def compare(bundle, device="cpu"):
    """``[(head, largest |difference|, relative to the largest |logit|, shape)]`` for every head of the
    golden file of ``bundle`` (a :class:`umgen_torch.Bundle`, or its path: opened on ``device``)."""
    bundle = bundle if isinstance(bundle, Bundle) else load(bundle, device)
    golden = bundle.path / "golden.safetensors"
    if not golden.exists():
        raise BundleError(f"{golden}: not there; export with `umgen export … --golden N`")
    with safe_open(golden, framework="pt") as st:
        want = {k: st.get_tensor(k) for k in st.keys()}
    got = bundle.logits(want.pop("tokens"))
    rows = []
    for head, expected in want.items():
        if head not in got:
            raise BundleError(f"{golden}: head `{head}` is not one this model has ({', '.join(sorted(got))})")
        mine = got[head].cpu()
        if head != "ego":
            mine = mine[:, -1]  # the golden file holds the last predicted frame of each window
        if mine.shape != expected.shape:
            raise BundleError(f"{golden}: `{head}` is {list(expected.shape)}, this runner gives {list(mine.shape)}")
        diff = (mine - expected).abs().max().item()
        rows.append((head, diff, diff / max(expected.abs().max().item(), 1e-30), list(expected.shape)))
    return rows


def main(argv=None):
    ap = argparse.ArgumentParser(prog="python -m umgen_torch.check", description=__doc__)
    ap.add_argument("bundle")
    ap.add_argument("--atol", type=float, default=1e-4, help="largest absolute difference allowed")
    ap.add_argument("--rtol", type=float, default=1e-5, help="largest relative difference allowed")
    ap.add_argument("--device", default="cpu", help="where the model runs (e.g. cuda; f32, no TF32)")
    a = ap.parse_args(argv)
    # f32 products stay f32 on a GPU (TF32 would round them to 10-bit mantissas).
    torch.backends.cuda.matmul.allow_tf32 = False
    try:
        rows = compare(a.bundle, a.device)
    except BundleError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    bad = 0
    print(f"{'head':<16} {'max |diff|':>12} {'relative':>12}  shape")
    for head, diff, rel, shape in rows:
        flag = "" if diff <= a.atol and rel <= a.rtol else "  past tolerance"
        bad += bool(flag)
        print(f"{head:<16} {diff:>12.3e} {rel:>12.3e}  {shape}{flag}")
    print(f"{len(rows) - bad} of {len(rows)} heads within atol {a.atol:g}, rtol {a.rtol:g}")
    return 1 if bad else 0


if __name__ == "__main__":
    sys.exit(main())
