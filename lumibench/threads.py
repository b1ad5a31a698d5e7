"""Thread settings the entry points apply before torch or Numba load (``python -m method``, ``python -m
benchmark``; the grid's workers inherit them).

- ``OMP_WAIT_POLICY=PASSIVE``: with active OpenMP waiting, idle pool threads spin; two one-thread grid
  workers on a 2-core box ran stage 1 ~7x slower (BENCHMARKS.md, "Wall time of the grid").
- ``NUMBA_NUM_THREADS`` from ``OMP_NUM_THREADS``: Numba starts a pool of one thread per core at import, and
  a process that runs its kernels on one thread (a grid worker) still woke the idle one at every parallel
  kernel (~25 % of the main thread's CPU time, 5-7 % of a ci stage 1's).
A value the user set is kept.
"""
from __future__ import annotations

import os


def configure_threads() -> None:
    os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
    omp = os.environ.get("OMP_NUM_THREADS", "").strip()
    if omp.isdigit() and int(omp) >= 1:
        os.environ.setdefault("NUMBA_NUM_THREADS", omp)
