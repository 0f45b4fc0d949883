"""rotavg_ros: filtered-DMF multiple rotation averaging for ROS 2.

Conventions throughout: ``R_i`` is the world-to-node rotation of node i and an edge
``(i, j)`` carries ``R_ij ~= R_i R_j^T`` (the orientation of frame j expressed in frame i).

Importing the package before numpy makes numpy's and scipy's OpenBLAS single-threaded
(unless ``OPENBLAS_NUM_THREADS`` is set): see :data:`BLAS_THREADS_VARIABLES`.
"""

import os as _os
import sys as _sys

__version__ = "0.1.0"

BLAS_THREADS_VARIABLES = ("OPENBLAS_NUM_THREADS",)
"""Set to 1 when this package is imported before numpy (every ``rotavg`` and
``rotavg_node`` process, and the node's solver child). The solver's numpy and scipy work is
many small products and factorizations; a multi-threaded BLAS spin-waits between them and
collapses when another process shares the CPU: the verification of Ellis Island took 23.9 s
with OpenBLAS's default 2 threads beside one busy process, 2.5 s with one (2-core machine).
A process that imports numpy first keeps its own setting, and its results can differ in
rounding from a ``rotavg`` process's (the BLAS's sums split across threads): a seed gives
bitwise-equal results for one BLAS thread count (the regime case Ellis + 30% at draw 1:
3.347 / 0.420 deg single-threaded, 3.339 / 0.425 deg with two threads). (Not
``MKL_NUM_THREADS``: torch reads it for its own thread count, which the solver sets per
fit.)"""

if "numpy" not in _sys.modules:
    for _name in BLAS_THREADS_VARIABLES:
        _os.environ.setdefault(_name, "1")
