"""A layered (Sugiyama-style) layout of a graph, for drawing it left to right.

Pure computation: node names and edges in, coordinates out. Cycles (loops in a UMRF graph)
are broken by a depth-first search from the sources; the edges it reverses are reported as
*back* edges so the page can draw them differently. Layers come from the longest path from a
source, and the order inside a layer from a few barycentre sweeps, which keeps edge crossings
low on the graphs people write by hand (tens of actions). Everything is linear in the size of
the graph per sweep.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from dataclasses import dataclass

__all__ = ["Layout", "layered_layout"]

#: Horizontal distance between layers, vertical distance between nodes of one layer, margin.
LAYER_GAP = 250.0  # the boxes are 150 wide: 100 between layers holds an edge's label
ROW_GAP = 70.0
MARGIN = 90.0

_SWEEPS = 4


@dataclass(frozen=True, slots=True)
class Layout:
    """Where each node goes.

    Attributes:
        positions: Centre ``(x, y)`` of each node, by name.
        layers: Layer index of each node (0: the sources).
        back_edges: The edges ``(src, dst)`` reversed to break cycles.
        width: Width of the drawing.
        height: Height of the drawing.
    """

    positions: dict[str, tuple[float, float]]
    layers: dict[str, int]
    back_edges: frozenset[tuple[str, str]]
    width: float
    height: float


def _back_edges(
    nodes: Sequence[str], succ: dict[str, list[str]], has_pred: set[str]
) -> set[tuple[str, str]]:
    """Edges that close a cycle, found by an iterative depth-first search."""
    white, grey, black = 0, 1, 2
    color = dict.fromkeys(nodes, white)
    back: set[tuple[str, str]] = set()
    # sources first, so that a loop is cut where it returns, not where it starts
    roots = [n for n in nodes if n not in has_pred] + list(nodes)
    for root in roots:
        if color[root] != white:
            continue
        color[root] = grey
        stack: list[tuple[str, int]] = [(root, 0)]
        while stack:
            node, i = stack[-1]
            children = succ[node]
            if i == len(children):
                color[node] = black
                stack.pop()
                continue
            stack[-1] = (node, i + 1)
            child = children[i]
            if color[child] == grey:
                back.add((node, child))
            elif color[child] == white:
                color[child] = grey
                stack.append((child, 0))
    return back


def layered_layout(nodes: Sequence[str], edges: Iterable[tuple[str, str]]) -> Layout:
    """Lay a directed graph out in layers, sources on the left.

    Args:
        nodes: Node names, in a stable order (it breaks ties).
        edges: ``(src, dst)`` pairs; edges naming unknown nodes and self-loops are ignored
            for the layout (self-loops are reported as back edges).

    Returns:
        The layout.

    Raises:
        ValueError: If a node name appears twice.
    """
    if len(set(nodes)) != len(nodes):
        raise ValueError("node names must be unique")
    known = set(nodes)
    succ: dict[str, list[str]] = {n: [] for n in nodes}
    has_pred: set[str] = set()
    loops: set[tuple[str, str]] = set()
    seen: set[tuple[str, str]] = set()
    for src, dst in edges:
        if src not in known or dst not in known or (src, dst) in seen:
            continue
        seen.add((src, dst))
        if src == dst:
            loops.add((src, dst))
            continue
        succ[src].append(dst)
        has_pred.add(dst)
    back = _back_edges(nodes, succ, has_pred)

    # longest path from a source over the forward edges (Kahn's order)
    fsucc = {n: [c for c in succ[n] if (n, c) not in back] for n in nodes}
    fpred: dict[str, list[str]] = {n: [] for n in nodes}
    for n in nodes:
        for c in fsucc[n]:
            fpred[c].append(n)
    indegree = {n: len(fpred[n]) for n in nodes}
    layer = dict.fromkeys(nodes, 0)
    ready = [n for n in nodes if indegree[n] == 0]
    while ready:
        nxt: list[str] = []
        for n in ready:
            for c in fsucc[n]:
                layer[c] = max(layer[c], layer[n] + 1)
                indegree[c] -= 1
                if indegree[c] == 0:
                    nxt.append(c)
        ready = nxt

    count = max(layer.values(), default=-1) + 1
    rows: list[list[str]] = [[] for _ in range(count)]
    for n in nodes:
        rows[layer[n]].append(n)
    order = {n: float(i) for row in rows for i, n in enumerate(row)}

    def sweep(row: list[str], neighbours: dict[str, list[str]]) -> None:
        def key(n: str) -> tuple[float, float]:
            near = neighbours[n]
            if not near:
                return (order[n], order[n])
            return (sum(order[m] for m in near) / len(near), order[n])

        row.sort(key=key)
        for i, n in enumerate(row):
            order[n] = float(i)

    for _ in range(_SWEEPS):
        for row in rows[1:]:
            sweep(row, fpred)
        for row in reversed(rows[:-1]):
            sweep(row, fsucc)

    tallest = max((len(r) for r in rows), default=0)
    positions: dict[str, tuple[float, float]] = {}
    for i, row in enumerate(rows):
        offset = (tallest - len(row)) * ROW_GAP / 2
        for j, n in enumerate(row):
            positions[n] = (MARGIN + i * LAYER_GAP, MARGIN / 2 + offset + j * ROW_GAP)
    width = 2 * MARGIN + max(count - 1, 0) * LAYER_GAP
    height = MARGIN + max(tallest - 1, 0) * ROW_GAP
    return Layout(positions, layer, frozenset(back | loops), width, height)
