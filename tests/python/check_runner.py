"""The PyTorch runner (runners/python) against umgen on one bundle:

1. its logits of the bundle's golden file (umgen export --golden) within the tolerances of
   `python -m umgen_torch.check`;
2. its greedy frames equal umgen's (`umgen generate --top-k 1`, tokens.json) token for token;
3. a manifest with a setting it does not implement is refused, naming the setting, by `load` and by the
   check's command line;
4. its draw distributions are umgen's (generate/src/sampling.rs) on logits with known softmax.

usage: check_runner.py BUNDLE TOKENS_JSON
"""
import json, pathlib, shutil, sys, tempfile

import math

import numpy as np
import torch
import umgen_torch
from umgen_torch import check
from umgen_torch.sampling import Sampling

# Logits 0, ln 2, ln 3, masked, ln 4: probabilities 1:2:3:4, the masked id never.
logits = np.array([0.0, math.log(2), math.log(3), -np.inf, math.log(4)], dtype=np.float32)
def dist(s, present=None):
    d = s.distribution(logits) if present is None else s.distribution_present(logits, present)
    return [(i, round(p, 6)) for i, p in d]
assert dist(Sampling(top_k=0)) == [(4, 0.4), (2, 0.3), (1, 0.2), (0, 0.1)]
assert dist(Sampling(top_k=2)) == [(4, round(4 / 7, 6)), (2, round(3 / 7, 6))]
assert dist(Sampling(top_k=0, top_p=0.5)) == dist(Sampling(top_k=2))
assert dist(Sampling(top_k=0, top_p=0.3)) == [(4, 1.0)]
assert dist(Sampling(top_k=1)) == [(4, 1.0)]
# An agent slot's first token with pad = id 0: pad keeps its 0.1, the top 2 of the rest share 0.9 as 4:3.
assert dist(Sampling(top_k=2), present=0) == [(0, 0.1), (4, round(0.9 * 4 / 7, 6)), (2, round(0.9 * 3 / 7, 6))]
# The nucleus of the rest: id 4 keeps 0.4; top-p 0.6 of the rest's 0.6 keeps ids 2 and 1 (3:2 of 0.6).
assert dist(Sampling(top_k=0, top_p=0.6, top_p_rest=True)) == [(4, 0.4), (2, 0.36), (1, 0.24)]
assert dist(Sampling(top_k=0, top_p_rest=True)) == dist(Sampling(top_k=0))
# Ties go to the lower id.
assert Sampling(top_k=1).distribution(np.array([1.0, 2.0, 2.0], dtype=np.float32))[0][0] == 1
print("sampling: ok")

bundle, tokens = pathlib.Path(sys.argv[1]), json.loads(pathlib.Path(sys.argv[2]).read_text())

rows = check.compare(bundle)
for head, diff, rel, shape in rows:
    print(f"{head}: max |diff| {diff:.3e}, relative {rel:.3e}, {shape}")
    assert diff <= 1e-4 and rel <= 1e-5, head
heads = {r[0] for r in rows}
assert "ego" in heads and any(h.startswith("oar.") for h in heads) and any(h.startswith("tar.") for h in heads), heads

# The comparison sees a model that differs: one OAR head's weights moved by 1e-3.
b = umgen_torch.load(bundle)
with torch.no_grad():
    b.model.oar_heads.heads[0].weight.add_(1e-3)
moved = {r[0]: r[1] for r in check.compare(b)}
assert moved[f"oar.{b.labels[0]}"] > 1e-4 and moved[f"tar.{b.labels[0]}"] <= 1e-4, moved

b = umgen_torch.load(bundle)
c = tokens["context_frames"]
scenes = tokens["scenes"]
frames = len(scenes[0]) - c
assert c > 0 and frames > 0, (c, frames)
got = b.generate([s[:c] for s in scenes], frames=frames, sampling={l: {"top_k": 1} for l in b.labels})
for i, (want, mine) in enumerate(zip(scenes, got)):
    for k, (fw, fm) in enumerate(zip(want[c:], mine)):
        bad = [p for p, (x, y) in enumerate(zip(fw, fm)) if x != y]
        assert not bad, f"scene {i} frame {k}: positions {bad[:10]} differ ({[fw[p] for p in bad[:5]]} vs {[fm[p] for p in bad[:5]]})"
print(f"greedy: {len(scenes)} scene(s) × {frames} frame(s) identical")

with tempfile.TemporaryDirectory() as tmp:
    copy = pathlib.Path(tmp) / "bundle"
    shutil.copytree(bundle, copy)
    manifest = json.loads((copy / "manifest.json").read_text())
    manifest["config"]["backbone"]["kv_heads"] = 2
    (copy / "manifest.json").write_text(json.dumps(manifest))
    try:
        umgen_torch.load(copy)
        raise AssertionError("a bundle with backbone.kv_heads loaded")
    except umgen_torch.UnsupportedSetting as e:
        assert e.setting == "backbone.kv_heads" and "kv_heads" in str(e), str(e)
    assert check.main([str(copy)]) == 2
print("unsupported setting refused: ok")
