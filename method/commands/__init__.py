"""The verbs of `python -m method`."""
