"""Reads an umgen export bundle with Python's safetensors package: every tensor of model.safetensors has
the expected dtype and a shape with at least one element; the given module paths are there; every file the
manifest lists has its size and SHA-256.

usage: check_bundle.py BUNDLE EXPECTED_DTYPE(F32|BF16) NAME [NAME...]
"""
import hashlib, json, pathlib, sys

from safetensors import safe_open

bundle, dtype, names = pathlib.Path(sys.argv[1]), sys.argv[2], sys.argv[3:]
manifest = json.loads((bundle / "manifest.json").read_text())
for rel, f in manifest["files"].items():
    data = (bundle / rel).read_bytes()
    assert len(data) == f["bytes"] and hashlib.sha256(data).hexdigest() == f["sha256"], rel
with safe_open(bundle / "model.safetensors", framework="numpy") as st:
    keys = set(st.keys())
    for name in names:
        assert name in keys, f"{name} not in {sorted(keys)[:10]}..."
    for k in keys:
        sl = st.get_slice(k)
        assert sl.get_dtype() == dtype, (k, sl.get_dtype())
        assert all(d > 0 for d in sl.get_shape()), (k, sl.get_shape())
print(f"{len(keys)} tensors, dtype {dtype}: ok")
