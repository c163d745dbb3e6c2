"""Drawing a token from logits as umgen does: temperature, top-k, top-p (optionally cut from the ids after
the most likely one, ``top_p_rest``); an agent slot's first token keeps pad's untruncated share
(docs/control.md). Ids are ranked most likely first, ties by id, so that top-k 1 is
the greedy choice with the lowest id winning a tie."""

import math

import numpy as np


class Sampling:
    """One modality's draw settings (``top_k`` 0 keeps every id; ``top_p`` 1 is no nucleus; with
    ``top_p_rest`` the most likely id keeps its probability and the nucleus is cut from the others)."""

    def __init__(self, top_k=16, top_p=1.0, temperature=1.0, top_p_rest=False, what="sampling"):
        if not (temperature > 0 and math.isfinite(temperature)):
            raise ValueError(f"{what}.temperature = {temperature}: must be a positive number")
        if not (0 < top_p <= 1):
            raise ValueError(f"{what}.top_p = {top_p}: must be in (0, 1]")
        self.top_k, self.top_p, self.temperature = int(top_k), float(top_p), float(temperature)
        self.top_p_rest = bool(top_p_rest)

    def ranked(self, logits):
        ids = np.flatnonzero(np.isfinite(logits))
        order = ids[np.lexsort((ids, -logits[ids].astype(np.float64)))]
        if 0 < self.top_k < len(order):
            order = order[: self.top_k]
        return order

    def weighted(self, logits, order):
        x = logits[order].astype(np.float64)
        probs = np.exp((x - x[0]) / self.temperature)
        probs /= probs.sum()
        if self.top_p < 1.0:
            probs = nucleus(probs.tolist(), self.top_p, self.top_p_rest)
            order = order[: len(probs)]
        return list(zip(order.tolist(), list(probs)))

    def distribution(self, logits):
        """``[(id, probability)]``, most likely first."""
        order = self.ranked(logits)
        return self.weighted(logits, order) if len(order) else []

    def distribution_present(self, logits, pad):
        """The distribution of a token group's first id: ``pad`` keeps its share of the softmax over every
        finite logit, the values among the top k share the rest."""
        if self.top_k <= 1:
            return self.distribution(logits)
        finite = logits[np.isfinite(logits)].astype(np.float64)
        if not len(finite):
            return []
        top = finite.max()
        total = np.exp((finite - top) / self.temperature).sum()
        share = 0.0
        if pad < len(logits) and np.isfinite(logits[pad]):
            share = math.exp((float(logits[pad]) - top) / self.temperature) / total
        order = self.ranked(logits)
        order = order[order != pad]
        if not len(order):
            return [(pad, 1.0)]
        return [(pad, share)] + [(i, p * (1.0 - share)) for i, p in self.weighted(logits, order)]


def nucleus(probs, top_p, rest):
    """``probs`` (most likely first) cut to the top-p nucleus and rescaled, as umgen's
    ``sampling::nucleus``: with ``rest`` the first keeps its probability and the cut is made among the
    others against ``top_p`` of their mass ``1 - probs[0]``, which the kept ones share."""
    skip = 1 if rest and probs else 0
    share = 1.0 - probs[0] if skip else 1.0
    mass, keep = 0.0, len(probs)
    for i in range(skip, len(probs)):
        mass += probs[i]
        if mass >= top_p * share:
            keep = i + 1
            break
    probs = probs[:keep]
    kept = sum(probs[skip:])
    if kept > 0.0:
        probs[skip:] = [p / kept * share for p in probs[skip:]]
    return probs


def walk(dist, u):
    """The id at the uniform number ``u`` along ``dist`` (the last one where rounding leaves some over)."""
    if not dist:
        return 0
    for i, p in dist:
        if u < p:
            return i
        u -= p
    return dist[-1][0]
