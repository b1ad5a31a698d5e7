"""Thread settings the entry points apply before torch or Numba load (``python -m method``, ``python -m
benchmark``; the grid's workers inherit them).

- ``OMP_WAIT_POLICY=PASSIVE`` where a process runs on fewer threads than the cores (``OMP_NUM_THREADS``
  below them: a grid worker beside others; ``benchmark.jobgrid`` also sets it for its worker pool): with
  OpenMP's spinning wait, idle pool threads spin on cores other processes need, and two one-thread grid
  workers on a 2-core box ran stage 1 ~7x slower (BENCHMARKS.md, "Wall time of the grid"). A training alone
  on every core keeps OpenMP's default (a short spin, then sleep): the compiled kernels and the network's
  products hand the two threads back and forth dozens of times a step, and a sleeping thread's wake-up cost
  `make demo`'s stage 1 nearly half its time (116 s against 60 s, BENCHMARKS.md, "Stage 2 at 1.1x"). On a
  box shared with other work, ``OMP_WAIT_POLICY=PASSIVE`` in the environment restores the sleeping wait.
- ``NUMBA_NUM_THREADS`` from ``OMP_NUM_THREADS``: Numba starts a pool of one thread per core at import, and
  a process that runs its kernels on one thread (a grid worker) still woke the idle one at every parallel
  kernel (~25 % of the main thread's CPU time, 5-7 % of a ci stage 1's).
A value the user set is kept. Numba's count is left alone where Numba is already imported (an entry point's
``main`` imported into a running process, as the tests and a notebook do): the pool is sized at import, and
changing the variable afterwards makes Numba's next compilation fail ("Cannot set NUMBA_NUM_THREADS to a
different value once the threads have been launched"; `OMP_NUM_THREADS=1 make test` failed seven tests so).
"""
from __future__ import annotations

import os
import sys

from lumibench.machine import usable_cores


def configure_threads() -> None:
    omp = os.environ.get("OMP_NUM_THREADS", "").strip()
    if omp.isdigit() and int(omp) >= 1:
        if "numba" not in sys.modules:  # too late for Numba's pool, and a change now breaks its compiler
            os.environ.setdefault("NUMBA_NUM_THREADS", omp)
        if int(omp) < usable_cores():
            os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
