"""The built-in component actions (one ``<name>.py`` + ``<name>.umrf.json`` each)."""
