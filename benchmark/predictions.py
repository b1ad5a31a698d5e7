"""Moved to :mod:`lumibench.predictions` (the data contract shared by adapters and the benchmark);
re-exported here for existing imports."""
from lumibench.predictions import *  # noqa: F401,F403
from lumibench.predictions import _rgb  # noqa: F401
