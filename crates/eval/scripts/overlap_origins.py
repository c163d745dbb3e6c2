#!/usr/bin/env python3
"""How the overlaps of generated rollouts begin: `python3 crates/eval/scripts/overlap_origins.py DIR/scenes.json ...`.

For each `umgen generate` output, every run of consecutive frames in which two agents' boxes overlap (an
episode) is put down to how it began: in the first generated frame; with one of the two absent from the
frame before (a new agent entering on another: what the new-agent rule is for); or between two agents
present in both frames (an onset, as `umgen eval`'s collisions begun). It prints the episodes and the
overlapping pair-frames (what the collision rate counts, frame by frame) by origin, the onsets by geometry
(headings within 30 degrees of each other or opposed: parallel, side by side beyond 1 m of lateral offset
or in line; else crossing) and by speed before the step (standing below 1 m/s), and the agent categories
of the episodes. Boxes and the overlap test are `umgen_eval::collision`'s (separating axes; touching
edges do not overlap).
"""

import collections
import json
import math
import sys


def corners(a):
    c, s = math.cos(a["heading"]), math.sin(a["heading"])
    hl, hw = a["length"] / 2, a["width"] / 2
    return [(a["x"] + u * c - v * s, a["y"] + u * s + v * c) for u, v in ((hl, hw), (-hl, hw), (-hl, -hw), (hl, -hw))]


def overlap(a, b):
    pa, pb = corners(a), corners(b)
    for pp in (pa, pb):
        for e in range(2):
            ax, ay = -(pp[e + 1][1] - pp[e][1]), pp[e + 1][0] - pp[e][0]
            pa_ = [x * ax + y * ay for x, y in pa]
            pb_ = [x * ax + y * ay for x, y in pb]
            if max(pa_) <= min(pb_) or max(pb_) <= min(pa_):
                return False
    return True


def onset_kind(a, b, a0, b0):
    dh = abs((a["heading"] - b["heading"] + math.pi) % (2 * math.pi) - math.pi)
    if dh < math.radians(30) or dh > math.radians(150):
        dx, dy = b["x"] - a["x"], b["y"] - a["y"]
        lateral = abs(-math.sin(a["heading"]) * dx + math.cos(a["heading"]) * dy)
        geometry = "parallel, side by side" if lateral > 1.0 else "parallel, in line"
    else:
        geometry = "crossing"
    va, vb = math.hypot(a0["vx"], a0["vy"]), math.hypot(b0["vx"], b0["vy"])
    standing = sum(v < 1.0 for v in (va, vb))
    return geometry, ["both moving", "one standing", "both standing"][standing]


def origins(scenes):
    episodes, pair_frames, onsets, categories = (collections.Counter() for _ in range(4))
    agents = colliding = 0
    for scene in scenes:
        began, prev = {}, {}
        for t, frame in enumerate(scene["frames"]):
            cur = {a["track_id"]: a for a in frame["agents"]}
            ids, hit = sorted(cur), set()
            for i, p in enumerate(ids):
                for q in ids[i + 1 :]:
                    a, b = cur[p], cur[q]
                    if not overlap(a, b):
                        continue
                    hit |= {p, q}
                    if (p, q) not in began or began[(p, q)][1] != t - 1:
                        if t == 0:
                            how = "in the first frame"
                        elif p not in prev or q not in prev:
                            how = "a new agent entering on another"
                        else:
                            how = "onset"
                            onsets[onset_kind(a, b, prev[p], prev[q])] += 1
                        episodes[how] += 1
                        categories[tuple(sorted((str(a["category"]), str(b["category"]))))] += 1
                        began[(p, q)] = (how, t)
                    else:
                        began[(p, q)] = (began[(p, q)][0], t)
                    pair_frames[began[(p, q)][0]] += 1
            agents += len(cur)
            colliding += len(hit)
            prev = cur
    return episodes, pair_frames, onsets, categories, colliding / max(agents, 1)


def main():
    if len(sys.argv) < 2:
        sys.exit(__doc__)
    for path in sys.argv[1:]:
        with open(path) as f:
            episodes, pair_frames, onsets, categories, share = origins(json.load(f))
        print(f"{path}: share of agents overlapping another {share:.4f}")
        for how in sorted(episodes, key=lambda k: -episodes[k]):
            print(f"  {how}: {episodes[how]} episodes, {pair_frames[how]} pair-frames")
        print("  onsets: " + "; ".join(f"{g}, {s}: {n}" for (g, s), n in onsets.most_common()))
        print("  categories: " + "; ".join(f"{a}/{b}: {n}" for (a, b), n in categories.most_common()))


if __name__ == "__main__":
    main()
