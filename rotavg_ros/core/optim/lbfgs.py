"""A small L-BFGS minimiser on one flat torch tensor (sparse mode's optimiser).

Why not a library one: ``torch.optim.LBFGS`` imports ``torch._dynamo`` on first use
(1.5-2.5 s per process), and scipy's L-BFGS-B runs its vector algebra through OpenBLAS,
whose worker threads spin-wait and collapse when the CPU is shared (a 1000-node solve
beside two busy processes: 11.4 s, against 4.6 s with one BLAS thread). Here every
operation is a torch op, so ``torch.set_num_threads`` governs it like the rest of a fit.

Method: L-BFGS (Nocedal & Wright, Sec. 7.2) with the initial Hessian scaled by
s^T y / y^T y, and a backtracking line search on the Armijo condition from step 1. Pairs
with s^T y <= 1e-10 |s| |y| are not stored, so the implied Hessian stays positive definite
without a Wolfe search. The direction comes from the compact representation (Byrd, Nocedal
& Schnabel 1994; N&W Eq. 7.24), the same matrix as the two-loop recursion: a handful of
matrix-vector products with the stored pairs instead of 4m vector operations, each of which
costs torch's per-call overhead (on a 5,000-node pose graph the two-loop recursion took 1.7
ms of each 4 ms iteration).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import torch

LossAndGrad = Callable[[torch.Tensor], tuple[float, torch.Tensor]]


@dataclass
class LBFGSResult:
    """Minimiser, its loss, and the iterations (accepted steps) taken."""

    x: torch.Tensor
    loss: float
    iterations: int


def minimize_lbfgs(
    loss_and_grad: LossAndGrad, x0: torch.Tensor, max_iterations: int, history: int = 20,
    ftol: float = 1e-12, armijo: float = 1e-4, max_backtracks: int = 30,
    precondition: Callable[[torch.Tensor], torch.Tensor] | None = None,
) -> LBFGSResult:
    """Minimise a smooth function of the flat tensor ``x0`` (not modified).

    ``loss_and_grad(x)`` returns the loss and its gradient (a new tensor shaped like x).
    Stops after ``max_iterations`` steps, when a step lowers the loss by less than
    ``ftol * max(|loss|, 1)``, when the gradient vanishes, or when no step along the
    search direction satisfies the Armijo condition. ``precondition`` (optional) applies
    ``M^-1``, ``M`` an SPD estimate of the Hessian in the loss's own scale: it replaces the
    identity as the initial inverse Hessian (scaled by s^T y / y^T M^-1 y), and the first
    step is then the full ``-M^-1 g``.
    """
    x = x0.clone()
    f, g = loss_and_grad(x)
    pairs = CurvaturePairs(history, x, precondition)
    it = 0
    while it < max_iterations:
        d = pairs.direction(g)
        slope = float(g.dot(d))
        if slope >= 0.0:  # not a descent direction (numerical trouble): restart
            pairs.clear()
            d = -g
            slope = -float(g.dot(g))
        if slope == 0.0:
            break  # zero gradient
        step = 1.0 if len(pairs) or precondition is not None else (
            min(1.0, 1.0 / max(float(g.abs().sum()), 1e-30)))
        for _ in range(max_backtracks):
            x_new = x + step * d
            f_new, g_new = loss_and_grad(x_new)
            if f_new <= f + armijo * step * slope:
                break
            step *= 0.5
        else:
            break  # no acceptable step: as close as this search gets
        pairs.add(x_new - x, g_new - g)
        decrease = f - f_new
        x, f, g = x_new, f_new, g_new
        it += 1
        if decrease <= ftol * max(abs(f), 1.0):
            break
    return LBFGSResult(x, f, it)


class CurvaturePairs:
    """The last ``history`` curvature pairs ``(s, y)`` in fixed rows of two buffers, with
    their Gram matrices ``S^T Y`` and ``Y^T M^-1 Y`` kept up to date one row and column per
    new pair, so a direction costs a few matrix-vector products (and, with a
    preconditioner ``M^-1``, one application to the gradient and one to each new ``y``)."""

    def __init__(self, history: int, like: torch.Tensor,
                 precondition: Callable[[torch.Tensor], torch.Tensor] | None = None) -> None:
        self.precondition = precondition
        self.S = like.new_zeros(history, like.numel())
        self.Y = like.new_zeros(history, like.numel())
        self.MY = self.Y if precondition is None else like.new_zeros(history, like.numel())
        self.SY = like.new_zeros(history, history)  # SY[a, b] = s_a . y_b (buffer rows)
        self.YY = like.new_zeros(history, history)  # YY[a, b] = y_a . M^-1 y_b
        self.order: list[int] = []  # buffer rows, oldest pair first

    def __len__(self) -> int:
        return len(self.order)

    def clear(self) -> None:
        self.order.clear()

    def add(self, s: torch.Tensor, y: torch.Tensor) -> None:
        """Store the pair unless ``s^T y <= 1e-10 |s| |y|`` (curvature too small)."""
        sy = float(s.dot(y))
        if not sy > 1e-10 * float(s.norm() * y.norm()):
            return
        history = self.S.shape[0]
        row = self.order.pop(0) if len(self.order) == history else (
            min(set(range(history)) - set(self.order)))
        self.S[row] = s
        self.Y[row] = y
        if self.precondition is not None:
            self.MY[row] = self.precondition(y)
        self.SY[row] = self.Y @ s  # s_row . y_b
        self.SY[:, row] = self.S @ y  # s_a . y_row
        self.YY[row] = self.YY[:, row] = self.Y @ self.MY[row]
        self.order.append(row)

    def direction(self, g: torch.Tensor) -> torch.Tensor:
        """``-H g``, ``H`` the L-BFGS inverse-Hessian estimate of the stored pairs
        (``-M^-1 g`` when none is stored)."""
        Mg = g if self.precondition is None else self.precondition(g)
        if not self.order:
            return -Mg
        k = torch.tensor(self.order, device=g.device)
        SY = self.SY[k][:, k]  # oldest pair first
        last = self.order[-1]
        gamma = float(self.SY[last, last] / self.YY[last, last])
        Rt = torch.triu(SY)  # R: s_a . y_b for a <= b
        u = (self.S @ g)[k]  # products with every buffer row: no copy of the pairs
        v = gamma * (self.Y @ Mg)[k]
        # H0 = gamma M^-1; H g = H0 g + [S, H0 Y] W [u; v] with
        # W = [[R^-T (D + Y^T H0 Y) R^-1, -R^-T], [-R^-1, 0]] (N&W Eq. 7.24).
        Ru = torch.linalg.solve_triangular(Rt, u[:, None], upper=True)[:, 0]  # R^-1 u
        inner = torch.diagonal(SY) * Ru + gamma * (self.YY[k][:, k] @ Ru) - v
        top = torch.linalg.solve_triangular(Rt.T, inner[:, None], upper=False)[:, 0]
        cs = torch.zeros_like(self.SY[0])
        cy = torch.zeros_like(self.SY[0])
        cs[k] = top
        cy[k] = -gamma * Ru
        return -(gamma * Mg + cs @ self.S + cy @ self.MY)
