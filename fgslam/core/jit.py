"""Compiled numeric kernels: the one set of numba options every kernel of fgslam is compiled with.

Hot loops whose cost is Python and numpy call overhead (many small array operations per edge, per
patch, per vertex) are written as plain Python loops over rows and compiled by numba
(https://numba.pydata.org: LLVM machine code from a prebuilt wheel, no compiler on the user's
machine). The compiled function is the implementation: tests (finite-difference Jacobians
included) call it, not a numpy twin.

Options, and why:

- ``cache=True``: the machine code is stored on disk beside the module (``__pycache__``, or numba's
  per-user cache folder where that is read-only) and reused by later processes: the first run after
  an install pays the compilation (docs/benchmarks/startup.md), later runs load it.
- ``fastmath=False`` and no ``parallel``: IEEE arithmetic in the order written, no reassociated or
  contracted (FMA) sums and no reductions split over threads, so a kernel gives the same bytes at any
  load and on any x86-64 CPU.
- ``nogil=True``: a kernel releases the GIL (the loop-closure and global-BA threads run meanwhile).
- ``error_model="numpy"``: division by zero gives inf / NaN as in numpy (callers mask them).

A module that defines kernels imports numba (about 0.3 s): such modules are imported where a run
needs them (``# deferred`` imports), never on the way to a command's first check.
"""

from __future__ import annotations

import functools
import logging
import time
from collections.abc import Callable
from typing import Any, Protocol

logger = logging.getLogger(__name__)

KERNEL_OPTIONS = {"cache": True, "fastmath": False, "nogil": True, "error_model": "numpy"}


class Kernel(Protocol):
    """A compiled function (numba's dispatcher): called like the Python function, which stays available as
    ``py_func`` (plain arithmetic kernels also run on torch tensors through it)."""

    py_func: Callable[..., Any]

    def __call__(self, *args: Any) -> Any: ...


def kernel(func: Callable) -> Kernel:
    """``func`` compiled with :data:`KERNEL_OPTIONS` (numba's dispatcher: compiled per argument types at
    the first call, or loaded from the on-disk cache)."""
    import numba  # deferred: numba (only modules that define kernels need it)

    return numba.njit(**KERNEL_OPTIONS)(func)


def _identity(x):
    return x


@functools.cache
def warm_up() -> None:
    """Import numba and load its machine-code target, once per process (later calls: no work; the
    seconds it took are logged at debug level).

    The first kernel a process calls pays both (about 2 s here: the import, then the target's
    registries, initialised when the first compiled function loads from the cache). A run calls this
    before its first frame (:attr:`fgslam.frontends.base.Frontend.uses_compiled_kernels`), so that no
    frame pays it: the first frames' time and a live run's first latency stay those of the work."""
    t0 = time.perf_counter()
    kernel(_identity)(0)
    logger.debug("compiled kernels ready in %.2f s", time.perf_counter() - t0)
