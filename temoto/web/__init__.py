"""The live view: an operator console, served by the instance on localhost, for running graphs.

Layering: ``temoto.web`` reads an :class:`~temoto.core.engine.ActionEngine` (and its
registrar) through their public snapshots and one instrument; nothing in ``temoto.core``
imports it. It uses the standard library only (``http.server``), and the page has no external
assets. Importing it starts nothing: :class:`LiveView` starts its server when constructed.

Modules: :mod:`~temoto.web.layout` (a layered graph layout), :mod:`~temoto.web.view` (the JSON
answers), :mod:`~temoto.web.events` (engine events fanned out to clients, and each run's
timeline), :mod:`~temoto.web.robot` (the Robot Manager's robot, sampled),
:mod:`~temoto.web.server` (:class:`LiveView`, with its token-guarded controls),
:mod:`~temoto.web.replay` (``temoto view``: a recorded run in the same page); ``_page`` holds
the page.
"""

from __future__ import annotations

from temoto.web.server import LiveView

__all__ = ["LiveView"]
