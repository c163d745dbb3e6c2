#!/usr/bin/env python3
"""Checks a umgen run's TensorBoard event files with TensorBoard's own reader.

    check_tensorboard.py RUN/tb TAG STEPS

Fails unless TAG has one scalar per step 1..STEPS (or more, when runs were resumed) and every value is
finite. CI runs it through the `train_cli` test with UMGEN_TB_PYTHON pointing at a Python that has the
`tensorboard` package.
"""
import math
import sys

from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

log_dir, tag, steps = sys.argv[1], sys.argv[2], int(sys.argv[3])
acc = EventAccumulator(log_dir)
acc.Reload()
tags = acc.Tags()["scalars"]
assert tag in tags, f"{tag} not among {tags}"
events = acc.Scalars(tag)
seen = sorted({e.step for e in events})
assert seen[:steps] == list(range(1, steps + 1)), f"steps {seen[:10]}..."
assert all(math.isfinite(e.value) for e in events), "non-finite values"
print(f"tensorboard: {len(tags)} tags, {tag} at {len(seen)} steps, last {events[-1].value:.4f}")
