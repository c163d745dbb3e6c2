"""The UMGen TAR/OAR backbone (paper §3.2) in plain PyTorch, built from a bundle's manifest.

A frame is N token positions in segments (one per modality, each ``[start] content… [end]``).
1. Tokens embed with per-segment tables (projected where the table is a codebook's width), plus a
   position embedding, through an MLP; the TAR adds a frame (time) embedding.
2. The ego module predicts the next frame's action: learned queries attend to the ego history, then to
   the current frame's other segments.
3. The TAR sees each frame with its action block replaced by the next frame's, its map moved by that
   action (AMA) and, with ``track``, its agent slots moved one frame ahead; temporal (causal, per
   position) and spatial (within the frame) layers give the prior ``h`` of the next frame.
4. The OAR reads the next frame shifted by one position (a start vector first) plus ``h``, causally.
5. Heads (no bias) score each segment's content ids only.
"""

import torch
from torch import nn

from . import motion
from .layers import CrossBlock, SelfBlock, layer_norm


class SegmentTable(nn.Module):
    """One segment's rows: of the embedding width ``e``, or of a codebook's width ``dim`` projected to it."""

    def __init__(self, rows, e, dim=None):
        super().__init__()
        self.table = nn.Embedding(rows, dim or e)
        self.proj = nn.Linear(dim, e) if dim else None


class FrameEmbedding(nn.Module):
    """``e = MLP(table(z) + pos)`` per position (paper eq. 2)."""

    def __init__(self, spec, dims, e, d):
        super().__init__()
        self.blocks = [(s["block_start"], s["block_len"]) for s in spec["segments"]]
        self.tables = nn.ModuleList(
            SegmentTable(s["embed_vocab"], e, dim) for s, dim in zip(spec["segments"], dims)
        )
        self.pos = nn.Parameter(torch.zeros(spec["n"], e))
        self.fc1 = nn.Linear(e, d)
        self.fc2 = nn.Linear(d, d)

    def _lookup(self, s, ids):
        t = self.tables[s]
        x = t.table(ids)
        return t.proj(x) if t.proj is not None else x

    def _mlp(self, x):
        return self.fc2(nn.functional.gelu(self.fc1(x)))

    def forward(self, tokens):
        """Embeddings ``[..., N, d]`` of frames ``[..., N]``."""
        parts = [self._lookup(s, tokens[..., a : a + l]) for s, (a, l) in enumerate(self.blocks)]
        return self._mlp(torch.cat(parts, -2) + self.pos)

    def segment_of(self, p, l=1):
        return next(s for s, (a, n) in enumerate(self.blocks) if a <= p and p + l <= a + n)

    def at(self, p, ids):
        """Embeddings ``[m, l, d]`` of ids ``[m, l]`` at positions ``p..p + l`` of one segment's block."""
        l = ids.shape[1]
        s = self.segment_of(p, l)
        return self._mlp(self._lookup(s, ids) + self.pos[p : p + l])


class EgoModule(nn.Module):
    """Learned queries over the ego history (CA_hist), then over the current environment (CA_env)."""

    def __init__(self, cfg, seg, d):
        super().__init__()
        heads, ratio = cfg["heads"], cfg["mlp_ratio"]
        self.block = (seg["block_start"], seg["block_len"])
        self.last = seg["offset"] if cfg.get("ego_last") else None
        self.queries = nn.Parameter(torch.zeros(seg["tokens"], d))
        self.hist = nn.ModuleList(CrossBlock(d, heads, ratio) for _ in range(cfg["ego_hist_layers"]))
        self.env = nn.ModuleList(CrossBlock(d, heads, ratio) for _ in range(cfg["ego_env_layers"]))
        self.ln = layer_norm(d)
        self.head = nn.Linear(d, seg["vocab"], bias=False)

    def forward(self, e, last_only=False):
        """Logits ``[b, tq, q, vocab]`` of the actions of frames ``1..=t`` from embedded frames ``e``
        ``[b, t, N, d]`` (the last one alone with ``last_only``)."""
        b, t, n, d = e.shape
        start, length = self.block
        q = self.queries.shape[0]
        tq = 1 if last_only else t
        first = t - tq
        hist = e[:, :, start : start + length].reshape(b, t * length, d)
        x = self.queries.expand(b, tq, q, d).reshape(b, tq * q, d)
        if self.last is not None:
            x = x + e[:, first:, self.last : self.last + q].reshape(b, tq * q, d)
        rows = torch.arange(tq * q, device=e.device) // q + first
        cols = torch.arange(t * length, device=e.device) // length
        hidden = cols[None, :] > rows[:, None]
        for blk in self.hist:
            x = blk(x, hist, hidden)
        env = torch.cat([e[:, :, :start], e[:, :, start + length :]], 2)[:, first:]
        env = env.reshape(b * tq, n - length, d)
        x = x.reshape(b * tq, q, d)
        for blk in self.env:
            x = blk(x, env)
        logits = self.head(self.ln(x))
        return logits.reshape(b, tq, q, -1)


class TarBlock(nn.Module):
    def __init__(self, d, heads, ratio):
        super().__init__()
        self.temporal = SelfBlock(d, heads, ratio)
        self.spatial = SelfBlock(d, heads, ratio)

    def forward(self, x):
        b, t, n, d = x.shape
        x = self.temporal.over_time(x)
        return self.spatial(x.reshape(b * t, n, d), causal=False).reshape(b, t, n, d)


class TrackProjection(nn.Module):
    def __init__(self, d):
        super().__init__()
        self.input = nn.Linear(d, d)
        self.output = nn.Linear(d, d)


class Heads(nn.Module):
    def __init__(self, segments, d):
        super().__init__()
        self.content = [(s["offset"], s["tokens"]) for s in segments]
        self.heads = nn.ModuleList(nn.Linear(d, s["vocab"], bias=False) for s in segments)

    def logits(self, s, x):
        """Logits ``[..., tokens, vocab]`` of segment ``s`` from features ``[..., N, d]``."""
        off, n = self.content[s]
        return self.heads[s](x[..., off : off + n, :])


class UMGen(nn.Module):
    """The backbone of a bundle: ``cfg`` is the manifest's ``config.backbone``, ``spec`` its ``backbone``,
    ``dims`` per segment the width of its codebook table (projected to the embedding width), or ``None``
    for a table of the embedding width."""

    def __init__(self, cfg, spec, dims):
        super().__init__()
        d = cfg["d_model"]
        e = cfg.get("embed_dim") or d
        heads, ratio = cfg["heads"], cfg["mlp_ratio"]
        self.spec = spec
        self.embed = FrameEmbedding(spec, dims, e, d)
        self.time = nn.Parameter(torch.zeros(cfg["max_frames"], d))
        action = spec.get("action")
        self.ego = EgoModule(cfg, spec["segments"][action["segment"]], d) if action else None
        self.tar = nn.ModuleList(TarBlock(d, heads, ratio) for _ in range(cfg["tar_layers"]))
        self.ln_tar = layer_norm(d)
        self.oar_bos = nn.Parameter(torch.zeros(d))
        self.oar = nn.ModuleList(SelfBlock(d, heads, ratio) for _ in range(cfg["oar_layers"]))
        self.ln_oar = layer_norm(d)
        self.track = TrackProjection(d) if spec.get("track") else None
        self.tar_heads = Heads(spec["segments"], d)
        self.oar_heads = Heads(spec["segments"], d)

    def action_values(self, ids):
        """(dx, dy, dθ) at bin centres ``[b, t, 3]`` of action tokens ``[b, t, q]``."""
        bins = self.spec["action"]["bins"]
        lo = torch.tensor([b[0] for b in bins], dtype=torch.float32, device=ids.device)
        width = torch.tensor([(b[1] - b[0]) / b[2] for b in bins], dtype=torch.float32, device=ids.device)
        return (ids[..., :3].float() + 0.5) * width + lo

    def tar_prior(self, tokens, e, e_next, next_action):
        """The TAR output ``[b, t, N, d]`` for frames ``tokens`` ``[b, t, N]`` (embedded ``e``), given the
        embeddings ``e_next`` and action tokens ``next_action`` ``[b, t, q]`` of the frames after them."""
        spec = self.spec
        b, t, n, d = e.shape
        x = e.clone()
        if spec.get("action"):
            s = spec["segments"][spec["action"]["segment"]]
            a, l = s["block_start"], s["block_len"]
            x[:, :, a : a + l] = e_next[:, :, a : a + l]
        act = self.action_values(next_action) if next_action is not None else None
        moved = None
        if self.track is not None and act is not None:
            k = spec["track"]
            s = spec["segments"][k["segment"]]
            at, l = s["offset"], s["tokens"]
            st = k.get("stops")
            stops = None
            if st:
                p = spec["segments"][st["segment"]]
                stops = tokens[:, :, p["offset"] : p["offset"] + p["tokens"]]
            ids = motion.moved(tokens[:, :, at : at + l], act, k, stops)
            moved = (at, self.embed.at(at, ids.reshape(b * t, l)).reshape(b, t, l, d))
            x[:, :, at : at + l] = x[:, :, at : at + l] + self.track.input(moved[1])
        if spec.get("align") and act is not None:
            al = spec["align"]
            s = spec["segments"][al["segment"]]
            at, l = s["offset"], s["tokens"]
            grid = x[:, :, at : at + l].reshape(b * t, l, d)
            shifted = motion.align(grid, act.reshape(b * t, 3), al["rows"], al["cols"], al["cell_m"])
            x[:, :, at : at + l] = x[:, :, at : at + l] + shifted.reshape(b, t, l, d)
        x = x + self.time[:t].reshape(1, t, 1, d)
        for blk in self.tar:
            x = blk(x)
        h = self.ln_tar(x)
        if moved is not None:
            at, m = moved
            h[:, :, at : at + m.shape[2]] = h[:, :, at : at + m.shape[2]] + self.track.output(m)
        return h

    def oar_forward(self, w):
        x = w
        for blk in self.oar:
            x = blk(x, causal=True)
        return self.ln_oar(x)

    @torch.no_grad()
    def logits(self, tokens, actions=None):
        """Teacher-forced logits of windows ``tokens`` ``[b, t + 1, N]`` (frame ``i + 1`` predicted from
        frames ``0..=i``): ``{"tar.<label>": [b, t, tokens, vocab], "oar.<label>": …, "ego": [b, t, q,
        vocab]}``. ``actions`` ``[b, t, q]`` replaces the next frames' action tokens where the TAR reads
        them (AMA, moved slots); by default they are the window's own."""
        tokens = torch.as_tensor(tokens, dtype=torch.long)
        b, f, n = tokens.shape
        if f < 2 or n != self.spec["n"]:
            raise ValueError(f"windows of {f} frames × {n} tokens; need ≥ 2 frames × {self.spec['n']}")
        t = f - 1
        e_all = self.embed(tokens)
        e, e_next = e_all[:, :t], e_all[:, 1:]
        next_action = None
        if self.spec.get("action"):
            s = self.spec["segments"][self.spec["action"]["segment"]]
            next_action = tokens[:, 1:, s["offset"] : s["offset"] + s["tokens"]]
            if actions is not None:
                next_action = torch.as_tensor(actions, dtype=torch.long)
        h = self.tar_prior(tokens[:, :t], e, e_next, next_action)
        d = h.shape[-1]
        bos = self.oar_bos.expand(b * t, 1, d)
        w = torch.cat([bos, e_next.reshape(b * t, n, d)[:, : n - 1]], 1) + h.reshape(b * t, n, d)
        o = self.oar_forward(w)
        out = {}
        for i, seg in enumerate(self.spec["segments"]):
            label = seg["label"]
            out[f"tar.{label}"] = self.tar_heads.logits(i, h)
            out[f"oar.{label}"] = self.oar_heads.logits(i, o).reshape(b, t, seg["tokens"], -1)
        if self.ego is not None:
            out["ego"] = self.ego(e)
        return out
