"""CLI verbs of `python -m generator`."""
