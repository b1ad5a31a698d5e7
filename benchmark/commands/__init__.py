"""CLI verbs of `python -m benchmark`."""
