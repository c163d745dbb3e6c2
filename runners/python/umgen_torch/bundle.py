"""Opening an export bundle: the manifest, the checksums, the settings this runner implements, the
weights (docs/export-format.md)."""

import hashlib
import json
import pathlib

import torch
from safetensors import safe_open

from .model import UMGen

FORMAT, VERSION = "umgen-bundle", 1

# Every `config.backbone` key this runner implements, with the values it accepts (None: any). Training-only
# settings are accepted whatever their value: inference computes in f32 without dropout.
BACKBONE_KEYS = {
    "d_model": None, "heads": None, "embed_dim": None, "mlp_ratio": None, "dropout": None,
    "ego_hist_layers": None, "ego_env_layers": None, "tar_layers": None, "oar_layers": None,
    "max_frames": None, "action": None, "align": None, "ego_last": None, "track": None,
    "track_accel": None, "track_follow": None, "track_stops": None, "step_s": None, "precision": {"f32", "bf16", "bf16-linear"}, "ordinal_init": None,
}
SPEC_KEYS = {
    "": {"n", "segments", "action", "align", "track"},
    "segments": {"label", "block_start", "block_len", "offset", "tokens", "vocab", "embed_vocab", "ordinal"},
    "action": {"segment", "bins"},
    "align": {"segment", "rows", "cols", "cell_m"},
    "track": {"segment", "slot", "values", "fields", "step_s", "pad", "accel", "follow", "stops"},
    "follow": {"half_width_m", "cos_heading", "min_gap_m", "min_room_m", "onset_m_s2", "max_m_s2"},
    "stops": {"segment", "slot", "values", "fields", "state", "stop", "go", "gap_m"},
}
# burn's layer-norm parameter names, and PyTorch's.
NORM_NAMES = {"gamma": "weight", "beta": "bias"}
GENERATION_KEYS = {
    "": {"window", "sampling", "groups"},
    "sampling": {"top_k", "top_p", "temperature"},
    "groups": {"first", "size", "count", "pad", "values", "last", "keep", "boxes"},
    "boxes": {"fields", "ego", "max_boxes", "whole_frame"},
}


class BundleError(Exception):
    """A bundle that is missing, damaged, or not of this format."""


class UnsupportedSetting(BundleError):
    """A bundle with a setting this runner does not implement; ``setting`` names it."""

    def __init__(self, setting, value):
        self.setting = setting
        super().__init__(f"this runner does not implement `{setting}` = {json.dumps(value)}")


def _known(where, table, keys):
    for key, value in table.items():
        if key not in keys:
            raise UnsupportedSetting(f"{where}{key}", value)


def check_settings(manifest):
    """Raises :class:`UnsupportedSetting` for the first setting of ``manifest`` this runner lacks."""
    backbone = manifest["config"].get("backbone", {})
    _known("backbone.", backbone, BACKBONE_KEYS)
    for key, allowed in BACKBONE_KEYS.items():
        if allowed is not None and key in backbone and backbone[key] not in allowed:
            raise UnsupportedSetting(f"backbone.{key}", backbone[key])
    spec = manifest["backbone"]
    _known("manifest backbone.", spec, SPEC_KEYS[""])
    for seg in spec["segments"]:
        _known("manifest backbone.segments.", seg, SPEC_KEYS["segments"])
    for part in ("action", "align", "track"):
        if spec.get(part):
            _known(f"manifest backbone.{part}.", spec[part], SPEC_KEYS[part])
    for part in ("follow", "stops"):
        if spec.get("track") and spec["track"].get(part):
            _known(f"manifest backbone.track.{part}.", spec["track"][part], SPEC_KEYS[part])
    gen = manifest.get("generation")
    if gen is None:
        raise BundleError("the manifest has no `generation` section: export the bundle again with a newer umgen")
    _known("generation.", gen, GENERATION_KEYS[""])
    for name, s in gen["sampling"].items():
        _known(f"generation.sampling.{name}.", s, GENERATION_KEYS["sampling"])
    for g in gen["groups"]:
        _known("generation.groups.", g, GENERATION_KEYS["groups"])
        if g.get("boxes"):
            _known("generation.groups.boxes.", g["boxes"], GENERATION_KEYS["boxes"])


def _state_dict(path, model):
    """The bundle's tensors as ``model``'s state dict: f32, linear weights transposed (the bundle stores
    ``[in, out]``), layer norms' ``gamma``/``beta`` as ``weight``/``bias``."""
    linears = {f"{name}.weight" for name, m in model.named_modules() if isinstance(m, torch.nn.Linear)}
    norms = {name for name, m in model.named_modules() if isinstance(m, torch.nn.LayerNorm)}
    out = {}
    with safe_open(path, framework="pt") as st:
        for key in st.keys():
            value = st.get_tensor(key).float()
            owner, _, leaf = key.rpartition(".")
            if owner in norms:
                key = f"{owner}.{NORM_NAMES.get(leaf, leaf)}"
            if key in linears:
                value = value.t().contiguous()
            out[key] = value
    return out


class Bundle:
    """An opened bundle: ``manifest``, the ``model`` (f32, eval mode) and its generation rules."""

    def __init__(self, path, device="cpu", verify=True):
        self.path = pathlib.Path(path)
        manifest_path = self.path / "manifest.json"
        try:
            self.manifest = json.loads(manifest_path.read_text())
        except (OSError, ValueError) as e:
            raise BundleError(f"{manifest_path}: {e}") from e
        m = self.manifest
        if (m.get("format"), m.get("version")) != (FORMAT, VERSION):
            raise BundleError(
                f"{manifest_path}: format {m.get('format')} v{m.get('version')}, expected {FORMAT} v{VERSION}"
            )
        if verify:
            self.verify()
        check_settings(m)
        self.spec = m["backbone"]
        self.generation = m["generation"]
        weights = self.path / "model.safetensors"
        with safe_open(weights, framework="pt") as st:
            keys = set(st.keys())
            dims = [
                st.get_slice(f"embed.tables.{i}.table.weight").get_shape()[1]
                if f"embed.tables.{i}.proj.weight" in keys
                else None
                for i in range(len(self.spec["segments"]))
            ]
        self.model = UMGen(m["config"]["backbone"], self.spec, dims)
        state = _state_dict(weights, self.model)
        missing, unexpected = self.model.load_state_dict(state, strict=False)
        if missing or unexpected:
            raise BundleError(
                f"{weights}: tensors the manifest's model lacks {sorted(unexpected)[:5]}, "
                f"tensors it needs and the file lacks {sorted(missing)[:5]}"
            )
        self.model.eval().to(device)
        self.device = torch.device(device)

    def verify(self):
        """Every file the manifest lists is there with its size and SHA-256."""
        for rel, f in self.manifest["files"].items():
            p = self.path / rel
            try:
                data = p.read_bytes()
            except OSError as e:
                raise BundleError(f"{p}: listed in the manifest but unreadable: {e}") from e
            if len(data) != f["bytes"] or hashlib.sha256(data).hexdigest() != f["sha256"]:
                raise BundleError(f"{p}: does not match the manifest's size and checksum (damaged or replaced)")

    @property
    def labels(self):
        """Segment labels (modality names) in frame order."""
        return [s["label"] for s in self.spec["segments"]]

    def logits(self, tokens, actions=None):
        """Teacher-forced logits of windows ``[b, t + 1, N]`` (:meth:`UMGen.logits`)."""
        return self.model.logits(torch.as_tensor(tokens, device=self.device), actions)

    def generate(self, history, frames=1, sampling=None, seed=0, window=None, actions=None):
        """Continues each scene of ``history`` (per scene a list of frames of N ids; ``[]`` starts from
        nothing) by ``frames`` frames with the bundle's token rules; returns the new frames per scene.
        ``sampling`` maps modality names to ``{"top_k", "top_p", "temperature", "top_p_rest"}`` replacing the bundle's
        defaults (``top_k = 1`` is greedy); ``actions`` (per frame, per scene, the action ids) forces the
        ego motion. See :mod:`umgen_torch.generate`."""
        from .generate import Generator

        g = Generator(self, sampling=sampling, seed=seed, window=window)
        return g.roll_out(history, frames, actions)


def load(path, device="cpu"):
    """Opens the bundle at ``path`` (:class:`Bundle`)."""
    return Bundle(path, device)
