"""User errors: reported as one actionable line on stderr with exit code 2, never as a traceback."""
from __future__ import annotations

import sys
from typing import Callable, Sequence


class UserError(Exception):
    """A mistake in what the user asked for or supplied (unknown name, bad YAML, missing file).

    Subclasses may set another ``exit_code`` (a diverged training exits 3, still with one line)."""

    exit_code = 2


EXIT_USER_ERROR = 2


def run_cli(main: Callable[[Sequence[str] | None], int | None], argv: Sequence[str] | None = None) -> int:
    """Call ``main(argv)``; turn a UserError into one stderr line and exit code 2."""
    try:
        rc = main(argv)
    except UserError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return int(getattr(exc, "exit_code", EXIT_USER_ERROR))
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return 130
    return int(rc or 0)
