"""Transformer layers of the umgen backbone: pre-norm self- and cross-attention blocks with GELU MLPs.

Parameter names follow the bundle's (burn's module paths), so that a bundle loads with ``load_state_dict``
once linear weights are transposed and layer norms renamed (``bundle.py``).
"""

import math

import torch
from torch import nn
from torch.nn import functional as F

LN_EPS = 1e-5


def layer_norm(d):
    return nn.LayerNorm(d, eps=LN_EPS)


class Mlp(nn.Module):
    """``Linear(d → r·d)``, exact (erf) GELU, ``Linear(r·d → d)``."""

    def __init__(self, d, hidden):
        super().__init__()
        self.fc = nn.Linear(d, hidden)
        self.proj = nn.Linear(hidden, d)

    def forward(self, x):
        return self.proj(F.gelu(self.fc(x)))


class MultiHead(nn.Module):
    """Multi-head attention: queries from ``x``, keys and values from one product of ``ctx`` (the keys'
    columns first, then the values')."""

    def __init__(self, d, heads):
        super().__init__()
        self.heads = heads
        self.q = nn.Linear(d, d)
        self.kv = nn.Linear(d, 2 * d)
        self.proj = nn.Linear(d, d)

    def split(self, x):
        b, l, d = x.shape
        return x.reshape(b, l, self.heads, d // self.heads).transpose(1, 2)

    def project(self, x, ctx):
        d = x.shape[-1]
        kv = self.kv(ctx)
        return self.split(self.q(x)), self.split(kv[..., :d]), self.split(kv[..., d:])

    def attend(self, q, k, v, hidden=None, causal=False):
        """``softmax(q kᵀ / √dh) v``; ``hidden`` (bool, broadcast to the scores) hides keys, ``causal``
        hides keys after each query (bottom-right aligned)."""
        scores = q @ k.transpose(-1, -2) / math.sqrt(q.shape[-1])
        if causal:
            lq, lk = scores.shape[-2:]
            later = torch.ones(lq, lk, dtype=torch.bool, device=q.device).triu(lk - lq + 1)
            scores = scores.masked_fill(later, float("-inf"))
        if hidden is not None:
            scores = scores.masked_fill(hidden, float("-inf"))
        return self.merge(torch.softmax(scores, dim=-1) @ v)

    def merge(self, y):
        b, h, l, dh = y.shape
        return self.proj(y.transpose(1, 2).reshape(b, l, h * dh))

    def forward(self, x, ctx, hidden=None, causal=False):
        q, k, v = self.project(x, ctx)
        return self.attend(q, k, v, hidden, causal)


class SelfBlock(nn.Module):
    """``x + attn(ln(x))``, then ``x + mlp(ln(x))``."""

    def __init__(self, d, heads, ratio):
        super().__init__()
        self.ln1 = layer_norm(d)
        self.attn = MultiHead(d, heads)
        self.ln2 = layer_norm(d)
        self.mlp = Mlp(d, ratio * d)

    def forward(self, x, causal):
        n = self.ln1(x)
        x = x + self.attn(n, n, causal=causal)
        return x + self.mlp(self.ln2(x))

    def over_time(self, x):
        """The causal layer over time of ``x`` ``[b, t, n, d]``: each position attends over its own frames."""
        b, t, n, d = x.shape
        y = self.forward(x.transpose(1, 2).reshape(b * n, t, d), causal=True)
        return y.reshape(b, n, t, d).transpose(1, 2)

    def step(self, x, cache, pos):
        """The causal layer on positions ``pos..pos + l`` ``x`` ``[m, l, d]``; ``cache`` holds the keys and
        values of the positions before (``None`` at the start) and is returned extended."""
        n = self.ln1(x)
        q, k, v = self.attn.project(n, n)
        if cache is not None:
            k, v = torch.cat([cache[0], k], 2), torch.cat([cache[1], v], 2)
        x = x + self.attn.attend(q, k, v, causal=True)
        return x + self.mlp(self.ln2(x)), (k, v)


class CrossBlock(nn.Module):
    """``x + attn(ln(x), ln(ctx))``, then ``x + mlp(ln(x))``."""

    def __init__(self, d, heads, ratio):
        super().__init__()
        self.ln_q = layer_norm(d)
        self.ln_ctx = layer_norm(d)
        self.attn = MultiHead(d, heads)
        self.ln2 = layer_norm(d)
        self.mlp = Mlp(d, ratio * d)

    def forward(self, x, ctx, hidden=None):
        x = x + self.attn(self.ln_q(x), self.ln_ctx(ctx), hidden)
        return x + self.mlp(self.ln2(x))
