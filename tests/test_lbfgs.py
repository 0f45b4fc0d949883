"""The sparse mode's L-BFGS minimiser on functions with known minima."""

from __future__ import annotations

import torch

from rotavg_ros.core.optim.lbfgs import minimize_lbfgs


def test_ill_conditioned_quadratic_reaches_its_minimum() -> None:
    gen = torch.Generator().manual_seed(0)
    q, _ = torch.linalg.qr(torch.randn(50, 50, generator=gen, dtype=torch.float64))
    A = q @ torch.diag(torch.logspace(0, 4, 50, dtype=torch.float64)) @ q.T  # cond 1e4
    b = torch.randn(50, generator=gen, dtype=torch.float64)
    x_star = torch.linalg.solve(A, b)

    def f(x: torch.Tensor) -> tuple[float, torch.Tensor]:
        return float(0.5 * x @ A @ x - b @ x), A @ x - b

    x0 = torch.zeros(50, dtype=torch.float64)
    res = minimize_lbfgs(f, x0, max_iterations=1000)  # scipy's L-BFGS-B: 466 iterations
    assert float((res.x - x_star).abs().max()) < 1e-4  # from 0.78 at x0
    assert torch.equal(x0, torch.zeros(50, dtype=torch.float64))  # input untouched
    assert res.iterations < 1000  # stopped on ftol, not on the cap


def test_rosenbrock() -> None:
    def f(x: torch.Tensor) -> tuple[float, torch.Tensor]:
        a, b = x[0], x[1]
        loss = (1 - a) ** 2 + 100 * (b - a * a) ** 2
        grad = torch.stack([-2 * (1 - a) - 400 * a * (b - a * a), 200 * (b - a * a)])
        return float(loss), grad

    res = minimize_lbfgs(f, torch.tensor([-1.2, 1.0], dtype=torch.float64), 1000)
    assert torch.allclose(res.x, torch.ones(2, dtype=torch.float64), atol=1e-5)


def test_iteration_cap_is_respected() -> None:
    def f(x: torch.Tensor) -> tuple[float, torch.Tensor]:
        return float((x * x).sum()), 2 * x

    res = minimize_lbfgs(f, torch.full((3,), 5.0, dtype=torch.float64), 0)
    assert res.iterations == 0 and res.loss == 75.0
