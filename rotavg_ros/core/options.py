"""Options of the rotation averager (no solver logic here).

Conventions: rotations are world-to-node (``x_node = R_i x_world``); edges carry
``R_ij ~= R_i R_j^T``. The anchor node of each connected component gets identity.
"""

from __future__ import annotations

import math
import re
from collections.abc import Iterator
from dataclasses import dataclass, field
from typing import TypeGuard

import numpy as np

from rotavg_ros.core.types import ProgressFn
from rotavg_ros.errors import InputError


@dataclass
class SolverOptions:
    """Every knob of the filtered-DMF pipeline; defaults are the measured choices."""

    mode: str = "auto"
    """``dense``: the paper's DMF (near-zero init, entry-wise L1, Adam, Sec. IV-C
    reweighting). ``sparse``: chordal warm start, entry-wise Huber, L-BFGS (for chain-like
    SLAM graphs). ``auto``: sparse when the mean degree 2|E|/N < ``sparse_mean_degree``."""
    sparse_mean_degree: float = 10.0
    depths: tuple[int, ...] = (2, 4, 6, 8)
    """Candidate depths d (even); H has d/2 factors. The best by the Eq. 3 cost wins."""
    sparse_depths: tuple[int, ...] = (2,)
    """Depth candidates in sparse mode. Depth matters through DMF's implicit bias from a
    near-zero start; a warm-started L-BFGS fit of a smooth loss has none, so one is enough."""
    use_filter: bool = True
    """Spanning-tree edge filtering (ablation (a) turns it off)."""
    use_support_count: bool = True
    """Order tree edges by support count first (ablation (b): mean error only)."""
    explicit_constraint: bool = True
    """Rank-3 symmetric H H^T (ablation (c): vanilla 3N x 3N factors + eigendecomposition)."""
    reweighting: bool = True
    """IRLS-style reweighting of Sec. IV-C (ablation (d) turns it off)."""
    sigma: float = 0.2
    """Filter threshold on d_chord(R_ij, R_ij^tree) (0.2 = 8.1 deg)."""
    sigma_untested: float | None = 0.6
    """Threshold for edges on no triangle whose tree path is triangle-verified
    (0.6 = 24.5 deg, allowing for path drift); None never removes such edges."""
    iterations: int = 1000
    """Dense mode: Adam iterations at most (fewer when ``tolerance`` stops the fit)."""
    tolerance: float = 5e-4
    """Dense mode early stopping: relative change of H per 25 iterations below which the
    fit counts as converged (twice in a row, after the warm-up); 0 = run every iteration.
    On Ellis Island the depth-2 fit stops after about 600 of 1000 iterations (mean error
    +0.007 deg); deeper fits converge later and mostly run to the end."""
    dtype: str = "float32"
    """Dense mode: torch dtype of the Adam fit (``float32`` or ``float64``). float32 is
    about twice as fast (the full-width factors are memory-bound) and gave the same Ellis
    Island errors to 0.002 deg; sparse mode always runs in float64."""
    lr: float = 0.01
    reweight_every: int = 25
    """lambda: reweight every this many iterations ..."""
    warmup: int = 200
    """lambda_warm: ... after this many warm-up iterations."""
    init_scale: float = 1e-2
    huber_factor: float = 30.0
    """Sparse mode: Huber delta = this x median |entry residual| of the chordal start."""
    sparse_rounds: int = 8
    """Sparse mode: at most this many L-BFGS runs, with an outlier reweighting between."""
    sparse_inner_iterations: int = 300
    sparse_diagonal_weight: float = 10.0
    sparse_outlier_factor: float = 5.0
    """Sparse mode: edges whose noise-scaled residual exceeds this x the median are
    down-weighted between L-BFGS runs."""
    warm_iterations: int = 100
    """Dense mode, warm-started re-solve: Adam iterations (vs ``iterations`` cold). 100
    was as accurate as 150 (2000 nodes +1% edges: median 0.288 vs 0.291 deg; a 1000-node
    stream: 0.369 vs 0.394) in two thirds of the time; 50 lost accuracy."""
    warm_lr: float = 1e-3
    """Dense mode, warm-started re-solve: initial learning rate."""
    warm_min_known: float = 0.5
    """Warm start only when at least this fraction of a component's nodes is known."""
    hidden_width: int | None = None
    """Width of the hidden factors; None = 3N (the paper) up to ``max_full_width_nodes``,
    ``scalable_width`` above."""
    max_full_width_nodes: int = 300
    scalable_width: int = 64
    seed: int = 0
    device: str = "cpu"
    """Torch device: ``cpu``, ``cuda`` (or ``cuda:N``), or ``auto`` (CUDA when available)."""
    cuda_graphs: bool = True
    """CUDA, dense mode: record each fit's Adam step once as a CUDA graph and replay it
    (its ~40 small kernels otherwise cost more to launch than to run), and fit the depth
    candidates in parallel threads, each on its own stream."""
    threads: int | None = None
    """Torch CPU threads for the solve, split among the depth candidates fitted in
    parallel. None: one thread per candidate, as many candidates at once as there are
    CPUs (robust when the CPU is shared; see ``solver._thread_plan``)."""
    progress: ProgressFn | None = field(default=None, repr=False, compare=False)

    def validate(self) -> None:
        """Raise :class:`~rotavg_ros.errors.InputError` (a ``ValueError``) naming the first
        option whose value cannot work.

        Checks ranges only (no device probing: an unavailable CUDA device is reported
        when the solve starts).
        """
        reason = next(self._problems(), None)
        if reason is not None:
            raise InputError(f"invalid solver option: {reason}")

    def _problems(self) -> Iterator[str]:
        if self.mode not in ("auto", "dense", "sparse"):
            yield f"mode must be auto, dense or sparse, got {self.mode!r}"
        for name in ("depths", "sparse_depths"):
            depths = getattr(self, name)
            if not depths or any(not _is_int(d) or d < 2 or d % 2 for d in depths):
                yield f"{name} must be a non-empty list of even integers >= 2, got {depths!r}"
        for name in ("iterations", "warm_iterations", "reweight_every", "sparse_rounds",
                     "sparse_inner_iterations"):
            if not _is_int(getattr(self, name)) or getattr(self, name) < 1:
                yield f"{name} must be an integer >= 1, got {getattr(self, name)!r}"
        for name in ("warmup", "max_full_width_nodes"):
            if not _is_int(getattr(self, name)) or getattr(self, name) < 0:
                yield f"{name} must be an integer >= 0, got {getattr(self, name)!r}"
        for name in ("lr", "warm_lr", "init_scale", "sigma", "huber_factor",
                     "sparse_outlier_factor"):
            if not _positive(getattr(self, name)):
                yield f"{name} must be a finite number > 0, got {getattr(self, name)!r}"
        if self.sigma_untested is not None and not _positive(self.sigma_untested):
            yield f"sigma_untested must be None or a finite number > 0, " \
                  f"got {self.sigma_untested!r}"
        for name in ("tolerance", "sparse_mean_degree", "sparse_diagonal_weight"):
            value = getattr(self, name)
            if not (_is_number(value) and math.isfinite(value) and value >= 0):
                yield f"{name} must be a finite number >= 0, got {value!r}"
        if not (_is_number(self.warm_min_known) and 0.0 <= self.warm_min_known <= 1.0):
            yield f"warm_min_known must be in [0, 1], got {self.warm_min_known!r}"
        if self.dtype not in ("float32", "float64"):
            yield f"dtype must be float32 or float64, got {self.dtype!r}"
        if self.hidden_width is not None and (not _is_int(self.hidden_width)
                                              or self.hidden_width < 3):
            yield f"hidden_width must be None or an integer >= 3 (H has rank 3), " \
                  f"got {self.hidden_width!r}"
        if not _is_int(self.scalable_width) or self.scalable_width < 3:
            yield f"scalable_width must be an integer >= 3 (H has rank 3), " \
                  f"got {self.scalable_width!r}"
        if self.threads is not None and (not _is_int(self.threads) or self.threads < 1):
            yield f"threads must be None or an integer >= 1, got {self.threads!r}"
        if not _DEVICE.fullmatch(str(self.device)):
            yield f"device must be cpu, cuda, cuda:N or auto, got {self.device!r}"
        if not _is_int(self.seed) or self.seed < 0:
            yield f"seed must be an integer >= 0, got {self.seed!r}"


_DEVICE = re.compile(r"cpu|auto|cuda(:\d+)?")


def _is_int(value: object) -> bool:
    return isinstance(value, (int, np.integer)) and not isinstance(value, bool)


def _is_number(value: object) -> TypeGuard[float]:
    return isinstance(value, (int, float, np.integer, np.floating)) and not isinstance(
        value, bool)


def _positive(value: object) -> bool:
    return _is_number(value) and math.isfinite(value) and value > 0
