"""How many observations a GP's exact conditioning holds within a memory budget.

Apart from ``core.gp`` (whose package imports the whole numerical stack) so that a ``fit``
with nothing to do can compare budgets without loading it.
"""

from __future__ import annotations

import math

#: Bytes per entry of the n x n training covariance that a GP's exact conditioning holds at
#: its peak: K alone, built and factorised in place (``core.gp.MFGP``,
#: ``core.gp._numerics.cholesky_inplace``). Measured: 8.8 bytes per entry of peak RSS above
#: the process's baseline at 8,000 observations (24.0 when K, its factor and the kernel's
#: temporaries were separate arrays); 10 leaves a margin.
BYTES_PER_ENTRY = 10


def max_conditioned(max_memory: int | None) -> int | None:
    """Most observations exact conditioning holds within ``max_memory`` bytes (None: no cap).

    floor(sqrt(max_memory / BYTES_PER_ENTRY)), at least 1: the n x n covariance and its
    factor dominate the memory of conditioning.
    """
    if max_memory is None:
        return None
    return max(1, math.isqrt(int(max_memory) // BYTES_PER_ENTRY))
