"""The live view's page: one HTML document with inline CSS and JavaScript, no external assets.

The same page serves a live engine (``data-mode="live"``: JSON API, event stream, controls)
and a recorded run (``data-mode="replay"``: one ``/api/recording`` answer and a time slider).
It draws the graph fitted to its panel (drag to pan, wheel to zoom, *fit* to reset), a
timeline (Gantt chart) of every action run, the robot (map with pose, trail and goal; arm
joints against their limits; vehicle; driver health) and the selected action's details.

The script builds every element with ``textContent`` and ``setAttribute`` (never ``innerHTML``),
so graph names, parameters and log lines cannot inject markup. The server sends a Content
Security Policy that allows exactly this script and this style (by hash) and requests to the
same origin. Node colours come from CSS rules on each node's ``data-state`` attribute, so a state
change is one attribute write. Writes carry the token from the address the server printed
(``?token=``) in a header; the page moves it from the address bar to the tab's session storage.

The page's text lives in package data beside this module (``static/page.css``,
``static/page.js``, ``static/body.html``, read once with :mod:`importlib.resources` on first
use), so it is edited as CSS, JavaScript and HTML; this module adds the per-state colour rules
and puts the document together.
"""

from __future__ import annotations

from functools import cache
from importlib.resources import files

__all__ = ["MODES", "STATES", "css", "js", "page"]

#: Node states in legend order, with their fill and text colours.
STATES: tuple[tuple[str, str, str], ...] = (
    ("UNINITIALIZED", "#d9dde3", "#1f2937"),
    ("INITIALIZED", "#bfd3f2", "#1f2937"),
    ("RUNNING", "#2f7de1", "#ffffff"),
    ("PAUSE_REQUESTED", "#fde68a", "#1f2937"),
    ("PAUSED", "#f2b705", "#1f2937"),
    ("STOPPING", "#f59e57", "#1f2937"),
    ("FINISHED", "#2fa84f", "#ffffff"),
    ("BYPASSED", "#b9a6e8", "#1f2937"),
    ("ERROR", "#d63b3b", "#ffffff"),
)

_STATE_RULES = "\n".join(
    f'.node[data-state="{s}"] rect, .bar[data-state="{s}"] {{ fill: {fill}; }}\n'
    f'.node[data-state="{s}"] text {{ fill: {ink}; }}\n'
    f'.swatch[data-state="{s}"], .badge[data-state="{s}"] {{ background: {fill}; color: {ink}; }}'
    for s, fill, ink in STATES
)

_STATIC = "static"


@cache
def _asset(name: str) -> str:
    """The text of one of the page's files in ``temoto/web/static`` (read once)."""
    return files("temoto.web").joinpath(_STATIC, name).read_text(encoding="utf-8")


def css() -> str:
    """The page's style sheet: ``static/page.css`` and one rule set per node state."""
    return "\n" + _asset("page.css") + _STATE_RULES + "\n"


def js() -> str:
    """The page's script (``static/page.js``)."""
    return "\n" + _asset("page.js")


def __getattr__(name: str) -> str:
    """``CSS`` and ``JS``: the style sheet and the script, read on first use (no I/O at import)."""
    if name == "CSS":
        return css()
    if name == "JS":
        return js()
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


#: The page's modes.
MODES = ("live", "replay")


def page(mode: str = "live") -> str:
    """The whole HTML document.

    Args:
        mode: ``live`` (an engine's API and event stream) or ``replay`` (a recording).

    Returns:
        The page (static: the data comes from the JSON API).

    Raises:
        ValueError: An unknown mode.
    """
    if mode not in MODES:
        raise ValueError(f"unknown page mode {mode!r}")
    states = " ".join(s for s, _, _ in STATES)
    title = "TeMoto live view" if mode == "live" else "TeMoto replay"
    body = _asset("body.html")
    return (
        '<!DOCTYPE html>\n<html lang="en"><head><meta charset="utf-8">\n'
        '<meta name="viewport" content="width=device-width, initial-scale=1">\n'
        '<link rel="icon" href="data:,">\n'
        f"<title>{title}</title>\n"
        f"<style>{css()}</style></head>\n"
        f'<body data-mode="{mode}" data-states="{states}">\n{body}<script>{js()}</script>\n'
        "</body></html>\n"
    )
