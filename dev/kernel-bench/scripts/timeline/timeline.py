"""Reads the CSV that libtimeline.so writes (timeline.c) and prints, for each training step after the
first two, how long it spanned, how much of it the GPU was busy (kernels, copies and memsets of every
stream, overlaps counted once), its idle gaps and where they fell, the kernel time by family, and what the
host did in the same span (driver calls by name, waits for the GPU).

    python3 timeline.py TIMELINE.csv [MARK]

Steps are cut at each kernel whose name contains MARK (default umgen_sumsq_final: the gradients' norm,
once a step before AdamW)."""
import collections
import sys

SPINS = {'wait', 'umgen_wait'}

FAMILIES = [('umgen_wait', 'spin (waits for a stream)'), ('wait', 'spin (waits for a stream)'), ('flash2', 'flash2'), ('nvjet', 'cuBLAS'), ('gemm', 'cuBLAS'), ('umgen_norm', 'layer norm'), ('umgen_gelu', 'bias + GELU'),
            ('umgen_temporal', 'attention over time'), ('umgen_xent', 'cross-entropy'), ('adamw', 'AdamW'),
            ('sumsq', 'AdamW'), ('umgen_', 'umgen other'), ('elemwise', 'fused element-wise'),
            ('fused', 'fused element-wise'), ('cast', 'cast'), ('reduce', 'reduction'), ('scatter', 'scatter'),
            ('slice', 'slice'), ('copy', 'copy'), ('contiguous', 'copy'), ('matmul', 'cubecl matmul')]


def family(name):
    for key, label in FAMILIES:
        if key in name:
            return label
    return name[:48]


def load(path):
    kinds = collections.defaultdict(list)
    with open(path, errors='replace') as f:
        for line in f:
            parts = line.rstrip('\n').split(',', 5)
            if len(parts) == 6:
                kinds[parts[0]].append((int(parts[1]), int(parts[2]), int(parts[3]), int(parts[4]), parts[5]))
    for v in kinds.values():
        v.sort()
    return kinds


def busy_and_gaps(work, a, b):
    busy, end, gaps = 0, a, []
    for st, en, _, _, name in work:
        if en <= a or st >= b:
            continue
        st, en = max(st, a), min(en, b)
        if st > end:
            gaps.append((st - end, end, name))
        busy += max(0, en - max(st, end))
        end = max(end, en)
    if b > end:
        gaps.append((b - end, end, '(step end)'))
    return busy, gaps


def main():
    kinds = load(sys.argv[1])
    mark = sys.argv[2] if len(sys.argv) > 2 else 'umgen_sumsq_final'
    # Kernels that spin until another stream's work is done (the side streams' ordering, side.rs) are not work.
    work = sorted([k for k in kinds['K'] if k[4] not in SPINS] + kinds['M'] + kinds['Z'])
    marks = [k[0] for k in kinds['K'] if mark in k[4]]
    launch = {c: (st, en) for st, en, _, c, name in kinds['A'] if 'Launch' in name}
    print(f'{len(kinds["K"])} kernels, {len(kinds["A"])} driver calls, {len(marks)} steps marked')
    for i in range(2, len(marks) - 1):
        a, b = marks[i], marks[i + 1]
        span = b - a
        busy, gaps = busy_and_gaps(work, a, b)
        idle = sum(g for g, _, _ in gaps)
        print(f'\nstep {i}: {span / 1e6:.1f} ms, GPU busy {busy / 1e6:.1f} ms ({100 * busy / span:.0f} %), '
              f'idle {idle / 1e6:.1f} ms in {len(gaps)} gaps '
              f'({sum(g for g, _, _ in gaps if g > 20e3) / 1e6:.1f} ms in gaps over 20 us)')
        tenth = [0] * 10
        for g, at, _ in gaps:
            tenth[min(9, (at - a) * 10 // span)] += g
        print('  idle per tenth of the step (ms):', ' '.join(f'{t / 1e6:.1f}' for t in tenth))
        for g, at, name in sorted(gaps, reverse=True)[:6]:
            print(f'  gap {g / 1e3:7.0f} us at {(at - a) / 1e6:6.1f} ms, before {name[:70]}')
        # How far ahead of the GPU the host launched: kernel start less its launch call's end.
        leads = sorted(k[0] - launch[k[3]][1] for k in kinds['K'] if a <= k[0] < b and k[3] in launch)
        if leads:
            q = lambda p: leads[min(len(leads) - 1, int(p * len(leads)))] / 1e6
            print(f'  launch lead (kernel start - launch call end), ms: p10 {q(0.1):.2f} p50 {q(0.5):.2f} '
                  f'p90 {q(0.9):.2f}; under 20 us: {sum(1 for x in leads if x < 20e3)} of {len(leads)}')
        if i == len(marks) - 2:
            by, n = collections.Counter(), collections.Counter()
            for st, en, _, _, name in kinds['K']:
                if a <= st < b:
                    by[family(name)] += en - st
                    n[family(name)] += 1
            print('  kernel time by family (ms, launches):')
            for k, v in by.most_common(25):
                print(f'    {k:48s} {v / 1e6:8.2f} {n[k]:6d}')
            calls, cn = collections.Counter(), collections.Counter()
            for st, en, _, _, name in kinds['A']:
                if a <= st < b:
                    calls[name] += en - st
                    cn[name] += 1
            print('  driver calls (ms, count):')
            for k, v in calls.most_common(12):
                print(f'    {k:48s} {v / 1e6:8.2f} {cn[k]:6d}')
            waits = [(st - a, en - st, t) for st, en, _, _, t in kinds['S'] if a <= st < b and en - st > 50e3]
            print(f'  host waits over 50 us: {len(waits)}, {sum(w for _, w, _ in waits) / 1e6:.1f} ms')
            for at, w, t in waits[:20]:
                print(f'    at {at / 1e6:6.1f} ms: {w / 1e6:.2f} ms (type {t})')


main()
