"""Ablation (c), vanilla DMF: G_hat = W_1 ... W_d with every W in R^{3N x 3N} (no symmetry,
no bottleneck), the loss on the same blocks, and rotations recovered afterwards from the
top-3 eigenvectors of the symmetrised G_hat.
"""

from __future__ import annotations

from collections.abc import Callable

import torch

from rotavg_ros.core.dmf.common import DMFFit, FitSpec, FloatArray, IntArray, init_factors, lr_at
from rotavg_ros.core.options import DenseFitOptions


def fit_vanilla(
    num_nodes: int, i: IntArray, j: IntArray, R: FloatArray, w: FloatArray,
    s: DenseFitOptions, fit: FitSpec,
    progress: Callable[[int, float], None] | None = None,
) -> DMFFit:
    """Ablation (c): G_hat = W_1 ... W_d, all 3N x 3N, then top-3 eigenvectors.

    Both (i, j) and (j, i) blocks and the identity diagonal are fitted, since G_hat is not
    symmetric by construction. Materialises G_hat (3N x 3N): only for the ablation.
    """
    dev = fit.device
    gen = torch.Generator().manual_seed(fit.seed)
    n3 = 3 * num_nodes
    factors = init_factors([(n3, n3)] * fit.depth, s.init_scale, gen, dev)
    nodes = torch.arange(num_nodes, device=dev)
    ti = torch.cat([torch.as_tensor(i, device=dev), torch.as_tensor(j, device=dev), nodes])
    tj = torch.cat([torch.as_tensor(j, device=dev), torch.as_tensor(i, device=dev), nodes])
    tR0 = torch.as_tensor(R, dtype=torch.float64, device=dev)
    eye = torch.eye(3, dtype=torch.float64, device=dev).expand(num_nodes, 3, 3)
    tR = torch.cat([tR0, tR0.transpose(1, 2), eye])
    e = int(i.shape[0])
    w_edges = torch.as_tensor(w, dtype=torch.float64, device=dev).clone()
    opt = torch.optim.Adam(factors, lr=s.lr, fused=True)
    loss_val = float("nan")
    for step in range(s.iterations):
        for group in opt.param_groups:
            group["lr"] = lr_at(step, s)
        G = _chain(factors).view(num_nodes, 3, num_nodes, 3)
        P = G[ti, :, tj, :]
        D = P - tR
        weights = torch.cat([w_edges, w_edges, torch.full((num_nodes,), s.diagonal_weight,
                                                          dtype=torch.float64, device=dev)])
        loss = (weights * D.abs().sum(dim=(1, 2))).sum()
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        loss_val = float(loss.detach())
        if (s.reweighting and step + 1 > s.warmup
                and (step + 1 - s.warmup) % s.reweight_every == 0):
            with torch.no_grad():
                r = D[:e].pow(2).sum(dim=(1, 2)).sqrt() + D[e:2 * e].pow(2).sum(dim=(1, 2)).sqrt()
                tau = torch.median(r)
                w_edges *= torch.where(r > tau, tau / r.clamp_min(1e-12), torch.ones_like(r))
        if progress is not None and (step + 1) % 250 == 0:
            progress(step + 1, loss_val)
    with torch.no_grad():
        G = _chain(factors)
        G = 0.5 * (G + G.T)
        evals, evecs = torch.linalg.eigh(G)
        top = evecs[:, -3:] * evals[-3:].clamp_min(0).sqrt()
    return DMFFit(top.view(num_nodes, 3, 3).cpu().numpy(), w_edges.cpu().numpy(), loss_val)


def _chain(factors: list[torch.Tensor]) -> torch.Tensor:
    out = factors[0]
    for w in factors[1:]:
        out = out @ w
    return out
