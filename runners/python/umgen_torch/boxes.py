"""The new-agent rule: a slot filled in the new frame but empty in the newest history frame is dropped
(made pad) when its bird's-eye box overlaps one decoded before it in the frame (the ego's first) or the
frame already holds ``max_boxes`` boxes. With ``whole_frame`` an agent that existed before also drops
every new agent decoded before it whose box it overlaps. Agents that existed before are kept."""

import math


def decode_box(tokens, fields):
    """(x, y, heading, length, width) at bin centres of a group's tokens; ``None`` if one is not a value."""
    values = []
    for i, lo, hi, bins in fields:
        if i >= len(tokens) or tokens[i] >= bins:
            return None
        values.append(lo + (tokens[i] + 0.5) * (hi - lo) / bins)
    return tuple(values)


def corners(box):
    x, y, heading, length, width = box
    c, s = math.cos(heading), math.sin(heading)
    hl, hw = length / 2.0, width / 2.0
    return [(x + u * c - v * s, y + u * s + v * c) for u, v in ((hl, hw), (-hl, hw), (-hl, -hw), (hl, -hw))]


def _project(poly, axis):
    values = [p[0] * axis[0] + p[1] * axis[1] for p in poly]
    return min(values), max(values)


def overlap(a, b):
    """Whether two boxes overlap (separating axes; touching is not overlapping)."""
    pa, pb = corners(a), corners(b)
    for poly in (pa, pb):
        for i in range(2):
            e = (poly[i + 1][0] - poly[i][0], poly[i + 1][1] - poly[i][1])
            axis = (-e[1], e[0])
            a0, a1 = _project(pa, axis)
            b0, b1 = _project(pb, axis)
            if a1 <= b0 or b1 <= a0:
                return False
    return True


class FrameBoxes:
    """The boxes decoded so far in one scene's new frame, starting with the ego's at the origin."""

    def __init__(self, ego):
        # (box, first position of a new agent's group or None)
        self.boxes = [((0.0, 0.0, 0.0, ego[0], ego[1]), None)]

    def admit(self, start, tokens, spec, newborn):
        """Takes in a finished group starting at ``start``; returns whether it must be emptied and the
        first positions of the new agents before it that must be."""
        box = decode_box(tokens, spec["fields"])
        if box is None:
            return False, []
        emptied = []
        if newborn:
            if len(self.boxes) >= spec["max_boxes"] or any(overlap(o, box) for o, _ in self.boxes):
                return True, []
        elif spec.get("whole_frame", False):
            kept = []
            for o, at in self.boxes:
                if at is not None and overlap(o, box):
                    emptied.append(at)
                else:
                    kept.append((o, at))
            self.boxes = kept
        self.boxes.append((box, start if newborn else None))
        return False, emptied
