"""The built-in visualization action (``show_display.py`` + ``show_display.umrf.json``).

It needs a Visualization Manager on the engine's registrar (server ``"display"``).
"""
