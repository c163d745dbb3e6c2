#!/usr/bin/env python3
"""The PyTorch reference's steady training step by kernel, eager or compiled (docs/performance.md).

    python3 dev/kernel-bench/scripts/torch-time-step.py path/to/torch_umgen.py --preset small [--compile]

Builds the step as `torch_umgen.py train` does (same model, AdamW, bf16 autocast, inputs), runs
`--warmup` steps (compilation), times `--timed` steps (their median and the peak allocation, as
`torch_umgen.py train` reports them), then runs `--steps` steps under torch.profiler and prints the GPU
time of one step by kernel family (`kernel_families.py`, the families `gpu-time-step.sh` prints for umgen) and the
largest kernels. The total is kernel time only: compare it with the step time to see the idle GPU.
"""

import argparse
import collections
import importlib.util
import os
import statistics
import sys
import time

import torch

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from kernel_families import summary  # noqa: E402


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("reference", help="path to torch_umgen.py")
    ap.add_argument("--preset", default="small")
    ap.add_argument("--compile", action="store_true")
    ap.add_argument("--warmup", type=int, default=3)
    ap.add_argument("--timed", type=int, default=10)
    ap.add_argument("--steps", type=int, default=3)
    args = ap.parse_args()
    spec = importlib.util.spec_from_file_location("torch_umgen", args.reference)
    ref = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(ref)
    dev = torch.device("cuda")
    cfg = ref.make_cfg(args.preset)
    torch.manual_seed(0)
    B, T = cfg["batch"], cfg["frames"]
    with torch.device(dev):
        model = ref.UMGen(cfg)
    model.train()
    opt = torch.optim.AdamW(model.parameters(), lr=1e-4, weight_decay=0.01, fused=True)
    fwd = torch.compile(model) if args.compile else model
    tokens, actions = ref.rand_tokens(cfg, B, T + 1, dev), ref.rand_actions(cfg, B, T + 1, dev)

    def step():
        with torch.autocast("cuda", dtype=torch.bfloat16):
            loss = fwd(tokens, actions)
        loss.backward()
        opt.step()
        opt.zero_grad(set_to_none=True)

    for _ in range(args.warmup):
        step()
    torch.cuda.synchronize()
    torch.cuda.reset_peak_memory_stats(dev)
    times = []
    for _ in range(args.timed):
        t0 = time.perf_counter()
        step()
        torch.cuda.synchronize()
        times.append((time.perf_counter() - t0) * 1e3)
    median = statistics.median(times)
    peak = torch.cuda.max_memory_allocated(dev) / 2**30
    start = time.perf_counter()
    with torch.profiler.profile(activities=[torch.profiler.ProfilerActivity.CUDA]) as prof:
        for _ in range(args.steps):
            step()
        torch.cuda.synchronize()
    wall = (time.perf_counter() - start) * 1e3 / args.steps
    by, n = collections.Counter(), collections.Counter()
    for e in prof.events():
        if e.device_type == torch.autograd.DeviceType.CUDA:
            by[e.name] += e.device_time_total / 1e3 / args.steps
            n[e.name] += 1
    launches = {k: round(v / args.steps) for k, v in n.items()}
    mode = "compiled" if args.compile else "eager"
    tokens = B * T * ref.frame_len(cfg)
    print(f"PyTorch {mode}, preset {args.preset}: {median:.1f} ms a step (median of {args.timed}), "
          f"{tokens / median * 1e3:.0f} tokens/s, peak allocation {peak:.2f} GiB; "
          f"{wall:.1f} ms a step under the profiler")
    print(summary(dict(by), launches))


if __name__ == "__main__":
    main()
