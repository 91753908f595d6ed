"""The built-in robot actions (one ``<name>.py`` + ``<name>.umrf.json`` each)."""
