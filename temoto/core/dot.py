"""Graphviz DOT text of a UMRF graph, for people to look at.

:func:`graph_to_dot` draws ``graph_entry`` and ``graph_exit`` as circles, one box per action
(full name, type unless ``sync``, actor, input literals), and one edge per parent→child
relation labelled with its non-default conditions and its remaps. Non-required parents are
dashed; a relation written on one side only is drawn red. Optional node states colour the
boxes. :func:`render` runs Graphviz's ``dot`` program to turn the text into an image.

The output depends only on the graph (document order), so it can be compared in tests and
kept under version control.
"""

from __future__ import annotations

import json
import shutil
import subprocess
from collections.abc import Mapping
from pathlib import Path

from temoto.core.graph import UmrfGraph
from temoto.core.params import Parameter
from temoto.core.umrf import (
    DEFAULT_CONDITIONS,
    ENTRY_NAME,
    EXIT_NAME,
    ChildRelation,
    ParentRelation,
)

__all__ = ["STATE_COLORS", "graph_to_dot", "render"]

#: Fill colours of nodes by state name (node states and graph-level results).
STATE_COLORS: Mapping[str, str] = {
    "UNINITIALIZED": "white",
    "INITIALIZED": "gray90",
    "RUNNING": "lightskyblue",
    "PAUSE_REQUESTED": "khaki",
    "PAUSED": "gold",
    "STOPPING": "orange",
    "FINISHED": "palegreen",
    "BYPASSED": "gray75",
    "ERROR": "tomato",
}

_MAX_VALUE = 24  # characters of one input literal shown
_MAX_LITERALS = 6  # input literals shown per action


def quote(text: str) -> str:
    r"""Quote a string as a DOT ID or label.

    Backslashes and double quotes are escaped, line breaks become DOT's ``\\n`` and other
    control characters are shown as ``\\xNN``-style text, so any name is safe.

    Args:
        text: The raw text.

    Returns:
        The text in double quotes.
    """
    out: list[str] = []
    for ch in text:
        if ch == "\\":
            out.append("\\\\")
        elif ch == '"':
            out.append('\\"')
        elif ch == "\n":
            out.append("\\n")
        elif ch < " " or ch == "\x7f" or "\ud800" <= ch <= "\udfff":
            # Control characters and lone surrogates (not encodable as UTF-8) shown as text.
            out.append(f"\\\\x{ord(ch):02x}")
        else:
            out.append(ch)
    return '"' + "".join(out) + '"'


def _label(lines: list[str]) -> str:
    return quote("\n".join(lines))


def _shorten(text: str, limit: int = _MAX_VALUE) -> str:
    return text if len(text) <= limit else text[: limit - 1] + "…"


def _literal(param: Parameter) -> str:
    try:
        shown = json.dumps(param.value, ensure_ascii=False, separators=(",", ":"))
    except (TypeError, ValueError):
        shown = repr(param.value)
    return f"{param.name}={_shorten(shown)}"


def _conditions(rel: ParentRelation) -> list[str]:
    return [
        f"{result.value}→{response.value}"
        for result, response in rel.conditions.items()
        if DEFAULT_CONDITIONS.get(result) is not response
    ]


def _remaps(rel: ChildRelation | None) -> list[str]:
    return [f"{r.from_}→{r.to}" for r in rel.remap] if rel is not None else []


def _attrs(pairs: list[tuple[str, str]]) -> str:
    return ", ".join(f"{key}={value}" for key, value in pairs)


def graph_to_dot(graph: UmrfGraph, *, states: Mapping[str, str] | None = None) -> str:
    """Describe a graph in the Graphviz DOT language.

    Args:
        graph: The graph.
        states: Optional state name (``RUNNING``, ``FINISHED``, ``ERROR``, ...) by node full
            name (``graph_entry`` / ``graph_exit`` for the graph's own nodes); the nodes are
            filled with the state's colour (see :data:`STATE_COLORS`) and the state is shown.

    Returns:
        DOT text of a ``digraph``, ending with a newline.
    """
    states = states or {}
    lines = [
        f"digraph {quote(graph.name)} {{",
        f"  graph [label={quote(graph.name)}, labelloc=t, rankdir=TB, fontname=Helvetica];",
        "  node [shape=box, style=rounded, fontname=Helvetica, fontsize=10];",
        "  edge [fontname=Helvetica, fontsize=9];",
    ]

    def state_attrs(full: str) -> list[tuple[str, str]]:
        state = states.get(full)
        if state is None:
            return []
        color = STATE_COLORS.get(state)
        pairs = [("tooltip", quote(state))]
        if color is not None:
            pairs.append(("fillcolor", quote(color)))
        return pairs

    for name, shape in ((ENTRY_NAME, "circle"), (EXIT_NAME, "doublecircle")):
        pairs = [("shape", shape), ("label", quote(name.replace("_", "\n")))]
        extra = state_attrs(name)
        if extra:
            pairs += [("style", "filled"), *extra]
        lines.append(f"  {quote(name)} [{_attrs(pairs)}];")

    by_name: dict[str, int] = {}
    for i, act in enumerate(graph.actions):
        by_name.setdefault(act.full_name, i)
        text = [act.full_name]
        if act.type != "sync":
            text.append(f"type: {act.type}")
        if act.actor:
            text.append(f"actor: {act.actor}")
        literals = [_literal(p) for p in act.input_parameters.values() if p.has_value]
        text.extend(literals[:_MAX_LITERALS])
        if len(literals) > _MAX_LITERALS:
            text.append(f"(+{len(literals) - _MAX_LITERALS} more)")
        state = states.get(act.full_name)
        if state is not None:
            text.append(f"[{state}]")
        pairs = [("label", _label(text))]
        extra = state_attrs(act.full_name)
        if extra:
            pairs += [("style", quote("rounded,filled")), *extra]
        lines.append(f"  {quote(act.full_name)} [{_attrs(pairs)}];")

    for rel in graph.entry:
        pairs = []
        remaps = _remaps(rel)
        if remaps:
            pairs.append(("label", _label(remaps)))
        suffix = f" [{_attrs(pairs)}]" if pairs else ""
        lines.append(f"  {quote(ENTRY_NAME)} -> {quote(rel.full_name)}{suffix};")

    # Relations keyed by (parent, child) in order of first mention, both sides merged.
    order: dict[tuple[str, str], None] = {}
    pside: dict[tuple[str, str], ParentRelation] = {}
    cside: dict[tuple[str, str], ChildRelation] = {}
    for act in graph.actions:
        for crel in act.children:
            key = (act.full_name, crel.full_name)
            order.setdefault(key)
            cside.setdefault(key, crel)
        for prel in act.parents:
            key = (prel.full_name, act.full_name)
            order.setdefault(key)
            pside.setdefault(key, prel)
    for key in order:
        parent, child = key
        prel_, crel_ = pside.get(key), cside.get(key)
        pairs = []
        text = (_conditions(prel_) if prel_ is not None else []) + _remaps(crel_)
        if text:
            pairs.append(("label", _label(text)))
        if prel_ is not None and not prel_.required:
            pairs.append(("style", "dashed"))
        if prel_ is None or crel_ is None or parent not in by_name or child not in by_name:
            pairs.append(("color", "red"))
            pairs.append(("tooltip", quote("relation written on one side only")))
        suffix = f" [{_attrs(pairs)}]" if pairs else ""
        lines.append(f"  {quote(parent)} -> {quote(child)}{suffix};")

    for prel in graph.exit:
        pairs = []
        text = _conditions(prel)
        if text:
            pairs.append(("label", _label(text)))
        if not prel.required:
            pairs.append(("style", "dashed"))
        suffix = f" [{_attrs(pairs)}]" if pairs else ""
        lines.append(f"  {quote(prel.full_name)} -> {quote(EXIT_NAME)}{suffix};")
    lines.append("}")
    return "\n".join(lines) + "\n"


def render(dot_text: str, out_path: Path, fmt: str) -> None:
    """Render DOT text to a file with Graphviz's ``dot`` program.

    Args:
        dot_text: DOT text (from :func:`graph_to_dot`).
        out_path: The image file to write.
        fmt: A Graphviz output format: ``png``, ``svg``, ``pdf``, ...

    Returns:
        None.

    Raises:
        FileNotFoundError: If the ``dot`` program is not installed.
        RuntimeError: If ``dot`` fails (its error output is in the message).
    """
    program = shutil.which("dot")
    if program is None:
        raise FileNotFoundError(
            "the Graphviz 'dot' program is not installed; install Graphviz"
            " (e.g. 'apt-get install graphviz') to render graphs"
        )
    proc = subprocess.run(
        [program, f"-T{fmt}", "-o", str(out_path)],
        input=dot_text.encode("utf-8"),
        capture_output=True,
        check=False,
    )
    if proc.returncode != 0:
        stderr = proc.stderr.decode("utf-8", errors="replace").strip()
        raise RuntimeError(f"dot -T{fmt} failed (exit code {proc.returncode}): {stderr}")
