"""Whether the compiled in-cycle kernels (:mod:`models._skin_kernels`) can run here: they need numba.

numba comes with the ``offline`` extra. A runtime-only install without it runs the numpy versions of the same
computations (the same results, a few times slower per frame), so ``models`` imports numba only where it exists.
The solver and the guard ask this module, which imports neither of them; :mod:`models.kernels` compiles the
kernels ahead of the first daemon start.
"""

from __future__ import annotations

import functools
import importlib.util


@functools.cache
def kernels_available() -> bool:
    """True when numba is installed, so :mod:`models._skin_kernels` can be compiled and run."""
    return importlib.util.find_spec("numba") is not None
