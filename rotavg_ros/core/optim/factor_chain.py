"""The factor product H = W_1 W_2 ... W_k with a hand-written forward and backward pass.

The DMF loss depends on the factors only through ``H`` (3N x 3), so each step needs the
product and, given dL/dH, every dL/dW_m. Autograd would form ``W_m @ X`` with ``X`` only
three columns wide, which CPU BLAS runs several times slower than the same product
written as ``X^T W_m^T`` (3 rows). This class keeps everything in that transposed layout:

* suffix products ``S_m = W_m ... W_k`` are held as ``S_m^T = S_{m+1}^T W_m^T`` (3 x rows_m);
* backward: ``dW_m = dS_m S_{m+1}^T`` (an outer product of inner size 3) and
  ``dS_{m+1}^T = dS_m^T W_m``.

Gradients are written into preallocated ``.grad`` buffers so a ``torch.optim`` optimizer
can step the factors directly; nothing here builds an autograd graph.
"""

from __future__ import annotations

import torch


class FactorChain:
    """Factors ``W_1 ... W_k`` (leaf tensors) and the transposed suffix products."""

    def __init__(self, factors: list[torch.Tensor]) -> None:
        self.factors = factors
        for w in factors:
            w.grad = torch.zeros_like(w)
        self._suffix_t: list[torch.Tensor] = []

    @torch.no_grad()
    def forward(self) -> torch.Tensor:
        """``H^T`` (3 x rows of W_1), caching the suffix products for :meth:`backward`."""
        ws = self.factors
        suffix = [ws[-1].T.contiguous()]
        for w in reversed(ws[:-1]):
            suffix.append(suffix[-1] @ w.T)
        suffix.reverse()  # suffix[m] = S_m^T, suffix[0] = H^T
        self._suffix_t = suffix
        return suffix[0]

    @torch.no_grad()
    def backward(self, grad_h_t: torch.Tensor) -> None:
        """Set every ``W_m.grad`` from ``dL/dH^T`` (3 x rows of W_1); needs :meth:`forward`."""
        ws, suffix = self.factors, self._suffix_t
        g = grad_h_t.contiguous()
        for m, w in enumerate(ws):
            assert w.grad is not None
            if m + 1 == len(ws):
                w.grad.copy_(g.T)
            else:
                torch.mm(g.T, suffix[m + 1], out=w.grad)
                g = g @ w

    @torch.no_grad()
    def product(self) -> torch.Tensor:
        """``H`` (rows of W_1 x 3)."""
        return self.forward().T
