"""Learning-rate schedules shared by both stages."""
from __future__ import annotations

import math


def expon_lr(step: int, total: int, lr0: float, lr1: float) -> float:
    """Log-linear decay from lr0 at step 0 to lr1 at ``total`` (3DGS's exponential schedule)."""
    t = min(max(step / max(total, 1), 0.0), 1.0)
    return math.exp(math.log(lr0) * (1 - t) + math.log(lr1) * t)
