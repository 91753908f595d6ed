"""Strongly connected components of a directed graph given as successor lists.

A small graph algorithm of its own, used by :mod:`temoto.core.validation` to find cycles of
required relations and actions that wait for each other.
"""

from __future__ import annotations

__all__ = ["strongly_connected"]


def strongly_connected(succ: list[list[int]]) -> list[list[int]]:
    """Tarjan's strongly connected components, iterative (no recursion limit).

    Args:
        succ: Successor lists of nodes ``0..n-1``.

    Returns:
        The components (each a list of nodes), in reverse topological order.
    """
    n = len(succ)
    order = [-1] * n
    low = [0] * n
    on_stack = [False] * n
    stack: list[int] = []
    comps: list[list[int]] = []
    counter = 0
    for root in range(n):
        if order[root] != -1:
            continue
        order[root] = low[root] = counter
        counter += 1
        stack.append(root)
        on_stack[root] = True
        work = [(root, 0)]
        while work:
            v, pos = work[-1]
            edges = succ[v]
            if pos < len(edges):
                work[-1] = (v, pos + 1)
                w = edges[pos]
                if order[w] == -1:
                    order[w] = low[w] = counter
                    counter += 1
                    stack.append(w)
                    on_stack[w] = True
                    work.append((w, 0))
                elif on_stack[w] and order[w] < low[v]:
                    low[v] = order[w]
                continue
            work.pop()
            if work:
                u = work[-1][0]
                if low[v] < low[u]:
                    low[u] = low[v]
            if low[v] == order[v]:
                comp: list[int] = []
                while True:
                    w = stack.pop()
                    on_stack[w] = False
                    comp.append(w)
                    if w == v:
                        break
                comps.append(comp)
    return comps
