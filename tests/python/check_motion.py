"""The PyTorch runner's tracked-slot hint (`umgen_torch.motion.moved`) against umgen's on one case that
`crates/generate/tests/track_follow.rs` writes: the track spec as a manifest holds it (follow rule and
stop points), the agents' and the heads' ids, the next actions, and burn's moved ids with the stop points
and without them. The runner's ids must equal burn's, and differ from the ids without the points.

usage: check_motion.py CASE_JSON
"""
import json, pathlib, sys

import torch
from umgen_torch import motion

case = json.loads(pathlib.Path(sys.argv[1]).read_text())
b, t = case["shape"]
ids = torch.tensor(case["ids"], dtype=torch.long).reshape(b, t, -1)
heads = torch.tensor(case["heads"], dtype=torch.long).reshape(b, t, -1)
act = torch.tensor(case["actions"], dtype=torch.float32).reshape(b, t, 3)
track = case["track"]
got = motion.moved(ids, act, track, heads).reshape(-1).tolist()
want, without = case["want"], case["without_stops"]
bad = [i for i, (g, w) in enumerate(zip(got, want)) if g != w]
assert len(got) == len(want) and not bad, f"{len(bad)} ids differ, first at {bad[:5]}"
braked = sum(g != w for g, w in zip(got, without))
assert braked > 0, "the stop points changed no id"
print(f"motion with stop points: {len(got)} ids agree, {braked} changed by the points")
