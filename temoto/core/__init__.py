"""The executive layer: UMRF model, validation, graph evolution and the Action Engine.

Layering rule: ``temoto.core`` imports nothing from ``temoto.drivers``, ``temoto.managers`` or
``temoto.transport`` (middleware independence, thesis requirement C-2.4). Modules whose name
starts with ``_`` are private; ``_fast`` holds the hot paths that may be compiled.
"""
