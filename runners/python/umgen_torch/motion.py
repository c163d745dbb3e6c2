"""What the TAR sees moved one frame ahead by the next ego action (paper §3.2 and docs/export-format.md):
the map grid (AMA) and, with ``backbone.track``, each agent slot moved by its velocity.

The slot arithmetic runs in f32 in the order umgen's does, so that a value on a bin edge lands in the
same bin.
"""

import math

import torch
from torch.nn import functional as F


def align(features, action, rows, cols, cell_m):
    """Grid features ``[b, rows·cols, d]`` (row 0 ahead, column 0 left, ``cell_m`` metres per cell) moved
    into the frame reached by ``action`` ``[b, 3]`` = (dx, dy, dθ): the output at a cell is the input at
    ``R(dθ)·p + (dx, dy)``, bilinear, zero outside."""
    b, m, d = features.shape
    dev = features.device
    c_idx = torch.arange(cols, device=dev, dtype=torch.float32)
    r_idx = torch.arange(rows, device=dev, dtype=torch.float32)
    gx = ((2.0 * c_idx + 1.0) / cols - 1.0).repeat(rows).reshape(1, m, 1)
    gy = ((2.0 * r_idx + 1.0) / rows - 1.0).repeat_interleave(cols).reshape(1, m, 1)
    dx, dy, th = (action[:, k].reshape(b, 1, 1) for k in range(3))
    c, s = torch.cos(th), torch.sin(th)
    # Columns run along −y and rows along −x: in normalised units the map is [[c, s, −2dy/W], [−s, c, −2dx/H]].
    tx = dy * (-2.0 / (cols * cell_m))
    ty = dx * (-2.0 / (rows * cell_m))
    sx = c * gx + s * gy + tx
    sy = -s * gx + c * gy + ty
    grid = torch.cat([sx, sy], 2).reshape(b, rows, cols, 2)
    x = features.reshape(b, rows, cols, d).permute(0, 3, 1, 2)
    y = F.grid_sample(x, grid, mode="bilinear", padding_mode="zeros", align_corners=False)
    return y.permute(0, 2, 3, 1).reshape(b, m, d)


def _scalar(like, value):
    return torch.full_like(like, float(torch.tensor(value, dtype=torch.float32)))


def centre(ids, lo, hi, n):
    """Bin centres of ``ids`` for ``n`` bins over ``[lo, hi)``."""
    width = (hi - lo) / n
    return (ids.float() + 0.5) * torch.tensor(width, dtype=torch.float32) + torch.tensor(lo, dtype=torch.float32)


def _turned(cos, sin, a, b):
    """``(a, b)`` seen from a frame turned by θ (given cos θ, sin θ)."""
    return cos * a + sin * b, cos * b - sin * a


def _change(slots, action, track, vx, vy):
    """The velocity's change of each slot since the window's previous frame (turned into this frame by the
    ego's turn between them); zero on the first frame, for a slot empty before, and where keeping it would
    turn the velocity around."""
    b, t = slots.shape[:2]
    before = torch.cat([slots[:, :1], slots[:, : t - 1]], 1)
    (_, _), (_, _), (ivx, bvx), (ivy, bvy), _ = track["fields"]
    pvx, pvy = centre(before[..., ivx : ivx + 1], *bvx), centre(before[..., ivy : ivy + 1], *bvy)
    dtheta = action[:, :, 2:3]
    turn = torch.cat([torch.zeros_like(dtheta[:, :1]), dtheta[:, : t - 1]], 1).reshape(b, t, 1, 1)
    ux, uy = _turned(torch.cos(turn), torch.sin(turn), pvx, pvy)
    dvx, dvy = vx - ux, vy - uy
    ix = track["fields"][0][0]
    was_there = before[..., ix : ix + 1] < track["values"]
    ahead = ((vx + dvx) * vx + (vy + dvy) * vy) >= 0.0
    drop = ~(was_there & ahead)
    return dvx.masked_fill(drop, 0.0), dvy.masked_fill(drop, 0.0)


def _hardest(rule, me, leaders, gap):
    """The hardest braking ``[b, t, s, 1]`` each slot ``me`` (x, y, cos and sin of its heading, speed
    along it) needs for ``leaders`` (``[b, t, 1, j]`` x, y, cos, sin of their headings, velocity or None for
    standing ones, presence) to keep ``gap`` metres between centres: ``w² / 2r``, 0 where none leads."""
    x, y, c, s, speed = me
    lx, ly, lc, ls, velocity, present = leaders
    dx, dy = lx - x, ly - y
    along = dx * c + dy * s
    across = dy * c - dx * s
    same_way = lc * c + ls * s
    if velocity is None:
        closing = speed.expand_as(along)
    else:
        closing = speed - (velocity[0] * c + velocity[1] * s)
    room = torch.clamp(along - _scalar(along, gap), min=rule["min_room_m"])
    need = closing * closing / (room * 2.0)
    leads = (
        present
        & (along > 0.0)
        & (across.abs() <= rule["half_width_m"])
        & (same_way >= _scalar(same_way, rule["cos_heading"]))
        & (closing > 0.0)
    )
    return need.masked_fill(~leads, 0.0).amax(dim=3, keepdim=True)


def stop_points(ids, st):
    """The stop points of stop-segment ids ``[b, t, m·slot]`` (the manifest's ``track.stops``) as
    standing leaders ``[b, t, 1, m]``: a slot with a value x in a stop state, with no slot at the same x and
    y ids in a go state."""
    b, t, l = ids.shape
    m = l // st["slot"]
    slots = ids.reshape(b, t, m, st["slot"])

    def column(i):
        return slots[..., i : i + 1].transpose(2, 3)

    x, y, heading = (centre(column(i), *bins) for i, bins in st["fields"])
    state = column(st["state"])

    def any_of(ids):
        out = torch.zeros_like(state, dtype=torch.bool)
        for i in ids:
            out = out | (state == i)
        return out

    stop, go = any_of(st["stop"]), any_of(st["go"])
    xi, yi = column(st["fields"][0][0]), column(st["fields"][1][0])
    # Point j (dim 3) is released by a go slot g (dim 2) at its x and y ids.
    same = (xi == xi.transpose(2, 3)) & (yi == yi.transpose(2, 3))
    released = (same & go.transpose(2, 3)).any(dim=2, keepdim=True)
    present = (xi < st["values"]) & stop & ~released
    return (x, y, torch.cos(heading), torch.sin(heading), None, present)


def _follow(rule, dt, occupied, state, dvx, dvy, points=None):
    """The velocity changes ``(dvx, dvy)`` ``[b, t, s, 1]`` with the braking ``rule`` (the manifest's
    ``track.follow``) asks for over ``dt`` seconds where it is harder than the change along the slot's
    heading: the hardest ``w² / 2r`` over the slower slots ahead in its lane and the stop ``points``
    (leaders of :func:`stop_points` and their gap), op for op as umgen's."""
    x, y, vx, vy, heading = state
    c, s = torch.cos(heading), torch.sin(heading)

    def other(v):
        return v.transpose(2, 3)

    speed = vx * c + vy * s
    me = (x, y, c, s, speed)
    slots = (other(x), other(y), other(c), other(s), (other(vx), other(vy)), other(occupied))
    hardest = _hardest(rule, me, slots, rule["min_gap_m"])
    if points is not None:
        leaders, gap = points
        hardest = torch.maximum(hardest, _hardest(rule, me, leaders, gap))
    brakes = occupied & (hardest >= rule["onset_m_s2"])
    target = torch.maximum(torch.clamp(hardest, max=rule["max_m_s2"]) * (-dt), -speed)
    change = dvx * c + dvy * s
    delta = torch.clamp(target - change, max=0.0).masked_fill(~brakes, 0.0)
    return dvx + delta * c, dvy + delta * s


def moved(ids, action, track, stops=None):
    """Ids ``[b, t, slots·slot]`` of the tracked segment with every occupied slot moved by its velocity
    over ``step_s`` (by constant acceleration with ``accel``) into the frame reached by ``action`` ``[b, t,
    3]``, re-binned; a slot moved past the x or y range becomes all pad (when the spec has a pad).
    ``stops`` are the ids of ``track.stops``'s segment, which the follow rule brakes for."""
    b, t, l = ids.shape
    k = track["slot"]
    slots = ids.reshape(b, t, l // k, k)
    fields = track["fields"]

    def column(i):
        return slots[..., i : i + 1]

    x, y, vx, vy, heading = (centre(column(i), *bins) for i, bins in fields)
    dx, dy, dtheta = (action[:, :, c].reshape(b, t, 1, 1) for c in range(3))
    cos, sin = torch.cos(dtheta), torch.sin(dtheta)
    if track.get("accel") and t > 1:
        dvx, dvy = _change(slots, action, track, vx, vy)
    else:
        dvx, dvy = torch.zeros_like(vx), torch.zeros_like(vy)
    occupied = column(fields[0][0]) < track["values"]
    if track.get("follow"):
        st = track.get("stops")
        points = (stop_points(stops, st), st["gap_m"]) if st and stops is not None else None
        state = (x, y, vx, vy, heading)
        dvx, dvy = _follow(track["follow"], track["step_s"], occupied, state, dvx, dvy, points)
    ds = track["step_s"]
    px = x + (vx + dvx * 0.5) * ds - dx
    py = y + (vy + dvy * 0.5) * ds - dy
    nx, ny = _turned(cos, sin, px, py)

    def within(v, bins):
        lo, hi, _ = bins
        return (v >= lo) & (v < hi)

    stays = within(nx, fields[0][1]) & within(ny, fields[1][1])
    nvx, nvy = _turned(cos, sin, vx + dvx, vy + dvy)
    h = heading - dtheta
    h = h - torch.floor((h + math.pi) / _scalar(h, 2.0 * math.pi)) * (2.0 * math.pi)
    columns = [column(i) for i in range(k)]
    for (i, (lo, hi, n)), v in zip(fields, [nx, ny, nvx, nvy, h]):
        width = (hi - lo) / n
        # Divided element by element (not by a reciprocal), as umgen does.
        columns[i] = torch.floor((v - lo) / _scalar(v, width)).clamp(0, n - 1).long()
    out = torch.cat(columns, 3)
    if track.get("pad") is not None:
        out = out.masked_fill(~stays.expand(-1, -1, -1, k), track["pad"])
    return torch.where(occupied.expand(-1, -1, -1, k), out, slots).reshape(b, t, l)
