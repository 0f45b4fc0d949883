"""A small L-BFGS minimiser on one flat torch tensor (sparse mode's optimiser).

Why not a library one: ``torch.optim.LBFGS`` imports ``torch._dynamo`` on first use
(1.5-2.5 s per process), and scipy's L-BFGS-B runs its vector algebra through OpenBLAS,
whose worker threads spin-wait and collapse when the CPU is shared (a 1000-node solve
beside two busy processes: 11.4 s, against 4.6 s with one BLAS thread). Here every
operation is a torch op, so ``torch.set_num_threads`` governs it like the rest of a fit.

Method: the standard two-loop recursion over the last ``history`` pairs (Nocedal &
Wright, Alg. 7.4) with the initial Hessian scaled by s^T y / y^T y, and a backtracking
line search on the Armijo condition from step 1. Pairs with s^T y <= 1e-10 |s| |y| are
not stored, so the implied Hessian stays positive definite without a Wolfe search.
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
) -> LBFGSResult:
    """Minimise a smooth function of the flat tensor ``x0`` (not modified).

    ``loss_and_grad(x)`` returns the loss and its gradient (a new tensor shaped like x).
    Stops after ``max_iterations`` steps, when a step lowers the loss by less than
    ``ftol * max(|loss|, 1)``, when the gradient vanishes, or when no step along the
    search direction satisfies the Armijo condition.
    """
    x = x0.clone()
    f, g = loss_and_grad(x)
    s_hist: list[torch.Tensor] = []
    y_hist: list[torch.Tensor] = []
    rho_hist: list[float] = []
    it = 0
    while it < max_iterations:
        d = _direction(g, s_hist, y_hist, rho_hist)
        slope = float(g.dot(d))
        if slope >= 0.0:  # not a descent direction (numerical trouble): restart
            s_hist.clear()
            y_hist.clear()
            rho_hist.clear()
            d = -g
            slope = -float(g.dot(g))
        if slope == 0.0:
            break  # zero gradient
        step = 1.0 if s_hist else min(1.0, 1.0 / max(float(g.abs().sum()), 1e-30))
        for _ in range(max_backtracks):
            x_new = x + step * d
            f_new, g_new = loss_and_grad(x_new)
            if f_new <= f + armijo * step * slope:
                break
            step *= 0.5
        else:
            break  # no acceptable step: as close as this search gets
        s, y = x_new - x, g_new - g
        sy = float(s.dot(y))
        if sy > 1e-10 * float(s.norm() * y.norm()):
            s_hist.append(s)
            y_hist.append(y)
            rho_hist.append(1.0 / sy)
            if len(s_hist) > history:
                del s_hist[0], y_hist[0], rho_hist[0]
        decrease = f - f_new
        x, f, g = x_new, f_new, g_new
        it += 1
        if decrease <= ftol * max(abs(f), 1.0):
            break
    return LBFGSResult(x, f, it)


def _direction(g: torch.Tensor, s_hist: list[torch.Tensor], y_hist: list[torch.Tensor],
               rho_hist: list[float]) -> torch.Tensor:
    """-H g by the two-loop recursion (H: the L-BFGS inverse-Hessian estimate)."""
    q = g.clone()
    alphas = []
    for s, y, rho in zip(reversed(s_hist), reversed(y_hist), reversed(rho_hist), strict=True):
        a = rho * float(s.dot(q))
        q.add_(y, alpha=-a)
        alphas.append(a)
    if s_hist:
        q.mul_(1.0 / (rho_hist[-1] * float(y_hist[-1].dot(y_hist[-1]))))
    for s, y, rho, a in zip(s_hist, y_hist, rho_hist, reversed(alphas), strict=True):
        b = rho * float(y.dot(q))
        q.add_(s, alpha=a - b)
    return q.neg_()
