#!/usr/bin/env python3
"""Fails when a crate's modules import each other in a cycle.

Usage: module-cycles.py SRC_DIR...   (each a crate's `src/`)

A module is a file (`foo.rs`, `foo/mod.rs`). Module A depends on module B when A names B or an item of B:
a `use crate::…`, `use super::…` or `use self::…` path (groups expanded), a `crate::…`/`super::…` path in
the code, or a parent's `child::item`. A `mod child;` declaration is not a dependency, nor are the
crate root's re-exports, visibility paths (`pub(in crate::x)`) or comments. `super::` inside an indented
inline module (`mod tests { use super::*; }`) names the file's own module.
"""
import os
import re
import sys


def modules(root):
    found = {}
    for dirpath, _, files in os.walk(root):
        for f in files:
            if f.endswith('.rs'):
                path = os.path.join(dirpath, f)
                parts = os.path.relpath(path, root)[:-3].split(os.sep)
                if parts[-1] in ('lib', 'main', 'mod'):
                    parts = parts[:-1]
                found[tuple(parts)] = path
    return found


def edges_of(mods):
    def resolve(path):
        for n in range(len(path), -1, -1):
            if tuple(path[:n]) in mods:
                return tuple(path[:n])
        return None

    edges = {m: set() for m in mods}
    for m, path in mods.items():
        with open(path, encoding='utf-8') as fh:
            src = fh.read()
        src = re.sub(r'//[^\n]*', '', src)
        src = re.sub(r'pub\(in [\w:]+\)', 'pub', src)

        def absolute(base, parts):
            if base == 'crate':
                return list(parts)
            if base == 'self':
                return list(m) + list(parts)
            cur = list(m)[:-1]
            while parts and parts[0] == 'super':
                cur, parts = cur[:-1], parts[1:]
            return cur + list(parts)

        def add(target):
            if target is not None and target != m:
                edges[m].add(target)

        for mt in re.finditer(r'(?m)^(\s*)use\s+(crate|super|self)::([^;]+);', src):
            base, body = mt.group(2), mt.group(3).strip()
            if base == 'super' and len(mt.group(1)) >= 4:
                base = 'self'
            group = re.match(r'([\w:]*?)(?:::)?\{(.*)\}$', body, re.S)
            items = []
            if group:
                prefix = [x for x in group.group(1).split('::') if x]
                for it in re.split(r',(?![^{]*\})', group.group(2)):
                    it = re.sub(r'\{.*', '', it.strip()).split(' as ')[0]
                    if it:
                        items.append(prefix + [x for x in it.split('::') if x])
            else:
                items.append([x for x in body.split(' as ')[0].split('::') if x])
            for it in items:
                add(resolve(absolute(base, it)))
        code = re.sub(r'\buse\s+[^;]+;', '', src)
        for mt in re.finditer(r'\b(crate|super|self)((?:::\w+)+)', code):
            add(resolve(absolute(mt.group(1), [x for x in mt.group(2).split('::') if x])))
        declarations_removed = re.sub(r'\bmod\s+\w+;', '', src)
        for child in mods:
            if len(child) == len(m) + 1 and child[:-1] == m:
                if re.search(r'(?<![\w:])' + child[-1] + r'::\w', declarations_removed):
                    edges[m].add(child)
    edges[()] = set()
    return edges


def cycles(edges):
    index, low, stack, on, found, counter = {}, {}, [], set(), [], [0]
    sys.setrecursionlimit(10000)

    def visit(v):
        index[v] = low[v] = counter[0]
        counter[0] += 1
        stack.append(v)
        on.add(v)
        for w in edges[v]:
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                found.append(comp)

    for v in edges:
        if v not in index:
            visit(v)
    return found


def main(roots):
    bad = 0
    for root in roots:
        edges = edges_of(modules(root))
        for comp in cycles(edges):
            bad += 1
            names = sorted('::'.join(x) for x in comp)
            print(f'{root}: modules in a cycle: {", ".join(names)}')
            for a in comp:
                for b in sorted(edges[a]):
                    if b in comp:
                        print(f'    {"::".join(a)} -> {"::".join(b)}')
    if bad == 0:
        print(f'no module import cycles in {", ".join(roots)}')
    return 1 if bad else 0


if __name__ == '__main__':
    sys.exit(main(sys.argv[1:]))
