"""Benchmarks of rotavg_ros (``python -m benchmarks.<name>``)."""

import rotavg_ros  # noqa: F401  (first: single-threaded BLAS, see rotavg_ros.BLAS_THREADS_VARIABLES)
