"""Generation: one new frame at a time. The ego module proposes the action (or it is forced), the TAR
runs over the last ``window`` frames, and the OAR fills the frame position by position over a key/value
cache. Start and end tokens are placed; the action tokens are placed where the action is known; the
agent slots follow the bundle's token rules (manifest ``generation.groups``):

- a slot comes out whole: its first token a value or pad, after a pad only pad, the middle tokens values,
  the last one a category;
- ``keep``: in a slot filled in a scene's newest frame, a pad drawn by the OAR is redrawn from the TAR
  head (pad excluded from nothing: the TAR may end the agent);
- ``boxes``: the new-agent rule (:mod:`umgen_torch.boxes`).
"""

import numpy as np
import torch

from .boxes import FrameBoxes
from .sampling import Sampling, walk


class Generator:
    """Draws frames from a :class:`umgen_torch.Bundle`'s model with its generation settings."""

    def __init__(self, bundle, sampling=None, seed=0, window=None):
        self.model, self.spec, gen = bundle.model, bundle.spec, bundle.generation
        self.device = bundle.device
        self.window = int(window or gen["window"])
        if self.window < 1:
            raise ValueError("window = 0: need at least one frame")
        labels = [s["label"] for s in self.spec["segments"]]
        sampling = sampling or {}
        unknown = sorted(set(sampling) - set(labels))
        if unknown:
            raise ValueError(f"sampling for {unknown}: this model has {', '.join(labels)}")
        self.sampling = []
        for label in labels:
            settings = dict(gen["sampling"].get(label, {}))
            settings.update(sampling.get(label, {}))
            self.sampling.append(Sampling(**settings, what=f"sampling.{label}"))
        self.rng = np.random.default_rng(seed)
        self.slots = []
        for i, s in enumerate(self.spec["segments"]):
            for p in range(s["block_start"], s["block_start"] + s["block_len"]):
                if p < s["offset"]:
                    self.slots.append(("start", i, s["vocab"]))
                elif p >= s["offset"] + s["tokens"]:
                    self.slots.append(("end", i, s["vocab"] + 1))
                else:
                    self.slots.append(("content", i, p - s["offset"]))
        self.groups = gen["groups"]
        self.group = [None] * self.spec["n"]
        for gi, g in enumerate(self.groups):
            for k in range(g["count"] * g["size"]):
                self.group[g["first"] + k] = (g["first"] + (k // g["size"]) * g["size"], k % g["size"], gi)
        action = self.spec.get("action")
        self.action = None
        if action:
            s = self.spec["segments"][action["segment"]]
            self.action = (action["segment"], s["offset"], s["tokens"])
        self.new_agents = [0, 0]

    def roll_out(self, history, frames, actions=None):
        """``frames`` new frames for each scene of ``history`` (lists of frames of N ids, all of one length);
        returns them per scene. ``actions[k][scene]`` forces frame k's action ids."""
        history = [list(map(list, h)) for h in history]
        new = [[] for _ in history]
        for k in range(frames):
            forced = actions[k] if actions is not None else None
            frame = self.next_frame(history, forced)
            for h, n, f in zip(history, new, frame):
                h.append(f)
                n.append(f)
        return new

    def _draw(self, s, logits, ok, first_of_group):
        smp = self.sampling[s]
        masked = np.where(ok(np.arange(len(logits))), logits, -np.inf).astype(np.float32)
        if first_of_group is not None:
            dist = smp.distribution_present(masked, first_of_group)
        else:
            dist = smp.distribution(masked)
        return walk(dist, self.rng.random())

    def _allowed(self, p, row):
        """``("only", id)`` or ``("ids", test)`` for position ``p`` of a frame decoded up to ``row`` (umgen's
        per-position id limits come from control files, which this runner does not take)."""
        g = self.group[p]
        if g is None:
            return "ids", lambda ids: np.ones(len(ids), dtype=bool)
        start, j, gi = g
        grp = self.groups[gi]
        pad, values, (lo, hi) = grp["pad"], grp["values"], grp["last"]
        if j == 0:
            return "ids", lambda ids: (ids < values) | (ids == pad)
        if row[start] == pad:
            return "only", pad
        if j + 1 == grp["size"]:
            return "ids", lambda ids: (ids >= lo) & (ids < hi)
        return "ids", lambda ids: ids < values

    @torch.no_grad()
    def next_frame(self, history, forced=None):
        """The next frame of each scene (``forced``: per scene the action ids)."""
        m, n = len(history), self.spec["n"]
        t = len(history[0]) if m else 0
        if m == 0 or any(len(h) != t or any(len(f) != n for f in h) for h in history):
            raise ValueError(f"{m} scenes: each needs the same number of frames of {n} tokens")
        action, h = self._window_pass(history, forced)
        return self._decode(history, action, h)

    def _window_pass(self, history, forced):
        model, dev = self.model, self.device
        m, n = len(history), self.spec["n"]
        t = len(history[0])
        d = model.time.shape[1]
        if t == 0:
            return forced, torch.zeros(m, n, d, device=dev)
        w = min(t, self.window)
        tokens = torch.tensor([h[t - w :] for h in history], dtype=torch.long, device=dev)
        e = model.embed(tokens)
        action = forced
        if action is None and self.action is not None:
            logits = model.ego(e, last_only=True)[:, 0].float().cpu().numpy()
            s = self.action[0]
            action = [[self._draw(s, row, lambda ids: np.ones(len(ids), bool), None) for row in q] for q in logits]
        known = torch.zeros(m, 1, n, dtype=torch.long, device=dev)
        for p, slot in enumerate(self.slots):
            if slot[0] != "content":
                known[:, 0, p] = slot[2]
        if action is not None and self.action is not None:
            _, off, q = self.action
            known[:, 0, off : off + q] = torch.tensor(action, dtype=torch.long, device=dev)
        e_new = model.embed(known)
        e_next = torch.cat([e[:, 1:], e_new], 1)
        next_action = None
        if action is not None and self.action is not None:
            _, off, q = self.action
            next_action = torch.cat([tokens, known], 1)[:, 1 : w + 1, off : off + q]
        h = model.tar_prior(tokens, e, e_next, next_action)
        return action, h[:, w - 1]

    def _decode(self, history, action, h):
        model, spec = self.model, self.spec
        m, n = len(history), spec["n"]
        out = [[0] * n for _ in range(m)]
        caches = [None] * len(model.oar)
        keep = self._keep(history)
        newborn = self._newborn(history)
        boxes = [None] * m
        box_spec = next((g["boxes"] for g in self.groups if g.get("boxes")), None)
        if box_spec is not None:
            boxes = [FrameBoxes(box_spec["ego"]) for _ in range(m)]
        for p in range(n):
            if p == 0:
                w = model.oar_bos.expand(m, 1, -1) + h[:, :1]
            else:
                prev = torch.tensor([[r[p - 1]] for r in out], dtype=torch.long, device=self.device)
                w = model.embed.at(p - 1, prev) + h[:, p : p + 1]
            x = w
            for i, blk in enumerate(model.oar):
                x, caches[i] = blk.step(x, caches[i], p)
            o = model.ln_oar(x)[:, 0]
            kind, s, i = self.slots[p]
            if kind != "content":
                for r in out:
                    r[p] = i
            elif self.action is not None and action is not None and s == self.action[0] and i < len(action[0]):
                for r, a in zip(out, action):
                    r[p] = int(a[i])
            else:
                self._draw_position(p, s, o, h, out, keep)
            self._new_agent_rule(p, out, newborn, boxes)
        return out

    def _draw_position(self, p, s, o, h, out, keep):
        logits = self.model.oar_heads.heads[s](o).float().cpu().numpy()
        g = self.group[p]
        first = self.groups[g[2]]["pad"] if g is not None and g[1] == 0 else None
        for b, r in enumerate(out):
            kind, what = self._allowed(p, r)
            r[p] = what if kind == "only" else self._draw(s, logits[b], what, first)
        if keep[p] is None:
            return
        pad, scenes = keep[p]
        redraw = [b for b in range(len(out)) if scenes[b] and out[b][p] == pad]
        if not redraw:
            return
        tar = self.model.tar_heads.heads[s](h[:, p]).float().cpu().numpy()
        for b in redraw:
            kind, what = self._allowed(p, out[b])
            if kind == "ids":
                out[b][p] = self._draw(s, tar[b], what, first)

    def _new_agent_rule(self, p, out, newborn, boxes):
        g = self.group[p]
        if g is None:
            return
        start, j, gi = g
        grp = self.groups[gi]
        if j + 1 != grp["size"] or not grp.get("boxes"):
            return
        for b, r in enumerate(out):
            if r[start] == grp["pad"]:
                continue
            born = newborn[b][p]
            dropped, emptied = boxes[b].admit(start, r[start : p + 1], grp["boxes"], born)
            self.new_agents[0] += int(born)
            for first in emptied + ([start] if dropped else []):
                self.new_agents[1] += 1
                r[first : first + grp["size"]] = [grp["pad"]] * grp["size"]

    def _keep(self, history):
        """Per position: ``(pad, per scene whether the slot was filled in the newest frame)``."""
        keep = [None] * self.spec["n"]
        for g in self.groups:
            if not g.get("keep"):
                continue
            for p in range(g["first"], g["first"] + g["count"] * g["size"]):
                alive = [bool(h) and h[-1][p] != g["pad"] for h in history]
                if any(alive):
                    keep[p] = (g["pad"], alive)
        return keep

    def _newborn(self, history):
        """Per scene and position: the position's group was empty in the newest frame (or there is none)."""
        out = []
        for h in history:
            row = [False] * self.spec["n"]
            for p, g in enumerate(self.group):
                if g is not None:
                    row[p] = not h or h[-1][g[0]] == self.groups[g[2]]["pad"]
            out.append(row)
        return out
