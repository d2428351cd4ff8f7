#!/usr/bin/env python3
"""Import circles between the top-level modules of crates.

Usage: scripts/import-cycles.py CRATE/src [CRATE/src ...]

Reads every `crate::x` path (uses, calls, doc links) of each .rs file up to its first
`#[cfg(test)]`, groups files by top-level module (a.rs, a/b.rs and a/mod.rs are module `a`),
and prints every strongly connected component of more than one module. Exits 1 if any.
"""
import os
import re
import sys


def graph(root):
    mods = {}
    for dp, _, fs in os.walk(root):
        for f in fs:
            if not f.endswith('.rs'):
                continue
            p = os.path.join(dp, f)
            rel = os.path.relpath(p, root)[:-3].split(os.sep)
            if rel[-1] in ('mod', 'lib', 'main'):
                rel = rel[:-1]
            name = rel[0] if rel else 'lib'
            src = open(p, encoding='utf-8').read()
            i = src.find('#[cfg(test)]')
            if i >= 0:
                src = src[:i]
            mods.setdefault(name, set()).update(d for d in re.findall(r'crate::([a-z_0-9]+)', src) if d != name)
    return {m: {d for d in ds if d in mods} for m, ds in mods.items()}


def cycles(g):
    idx, low, stack, on, out, n = {}, {}, [], set(), [], [0]

    def visit(v):
        idx[v] = low[v] = n[0]
        n[0] += 1
        stack.append(v)
        on.add(v)
        for w in sorted(g[v]):
            if w not in idx:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], idx[w])
        if low[v] == idx[v]:
            comp = []
            while True:
                w = stack.pop()
                on.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                out.append(sorted(comp))

    for v in sorted(g):
        if v not in idx:
            visit(v)
    return out


bad = False
for root in sys.argv[1:]:
    g = graph(root)
    found = cycles(g)
    for comp in found:
        bad = True
        print(f'{root}: circle {" <-> ".join(comp)}: ' + ', '.join(f'{m} -> {sorted(g[m] & set(comp))}' for m in comp))
    if not found:
        print(f'{root}: no import circle among {len(g)} modules')
sys.exit(1 if bad else 0)
