"""The sparse mode's L-BFGS minimiser on functions with known minima."""

from __future__ import annotations

import torch

from rotavg_ros.core.optim.lbfgs import CurvaturePairs, minimize_lbfgs


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


def _two_loop(g: torch.Tensor, pairs: list[tuple[torch.Tensor, torch.Tensor]]) -> torch.Tensor:
    """The textbook two-loop recursion (Nocedal & Wright, Alg. 7.4): -H g."""
    q = g.clone()
    alphas = []
    for s, y in reversed(pairs):
        a = float(s.dot(q)) / float(s.dot(y))
        q -= a * y
        alphas.append(a)
    s, y = pairs[-1]
    q *= float(s.dot(y)) / float(y.dot(y))
    for (s, y), a in zip(pairs, reversed(alphas), strict=True):
        q += (a - float(y.dot(q)) / float(s.dot(y))) * s
    return -q


def test_compact_direction_equals_the_two_loop_recursion() -> None:
    gen = torch.Generator().manual_seed(1)
    A = torch.randn(40, 40, generator=gen, dtype=torch.float64)
    A = A @ A.T + torch.eye(40, dtype=torch.float64)  # SPD: every pair has s^T y > 0
    history = 5
    pairs = CurvaturePairs(history, torch.zeros(40, dtype=torch.float64))
    stored: list[tuple[torch.Tensor, torch.Tensor]] = []
    for _ in range(8):  # more pairs than the history: the buffer's rows get reused
        s = torch.randn(40, generator=gen, dtype=torch.float64)
        pairs.add(s, A @ s)
        stored = (stored + [(s, A @ s)])[-history:]
        g = torch.randn(40, generator=gen, dtype=torch.float64)
        assert torch.allclose(pairs.direction(g), _two_loop(g, stored), rtol=1e-9, atol=1e-12)
    pairs.add(torch.ones(40, dtype=torch.float64), -torch.ones(40, dtype=torch.float64))
    assert len(pairs) == history  # negative curvature: not stored
    pairs.clear()
    g = torch.randn(40, generator=gen, dtype=torch.float64)
    assert torch.equal(pairs.direction(g), -g)
