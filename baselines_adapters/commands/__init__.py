"""Verbs of ``python -m baselines_adapters`` (one module each: ``register(subparsers)``, ``run(args)``)."""
