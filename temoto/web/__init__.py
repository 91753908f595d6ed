"""The live view: a web page, served by the instance on localhost, showing running graphs.

Layering: ``temoto.web`` reads an :class:`~temoto.core.engine.ActionEngine` (and its
registrar) through their public snapshots and one instrument; nothing in ``temoto.core``
imports it. It uses the standard library only (``http.server``), and the page has no external
assets. Importing it starts nothing: :class:`LiveView` starts its server when constructed.

Modules: :mod:`~temoto.web.layout` (a layered graph layout), :mod:`~temoto.web.view` (the JSON
answers), :mod:`~temoto.web.events` (engine events fanned out to clients),
:mod:`~temoto.web.server` (:class:`LiveView`); ``_page`` holds the page.
"""

from __future__ import annotations

from temoto.web.server import LiveView

__all__ = ["LiveView"]
