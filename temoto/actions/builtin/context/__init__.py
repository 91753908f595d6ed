"""The built-in world-model actions (one ``<name>.py`` + ``<name>.umrf.json`` each).

They need a Context Manager on the engine's registrar (server ``"context"``).
"""
