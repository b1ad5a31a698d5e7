"""Shared plumbing for the LumiBench packages: user errors, YAML validation, atomic I/O, progress."""
