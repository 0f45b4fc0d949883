"""Adam for the DMF factors, without ``torch.optim``.

``torch.optim``'s optimizers import ``torch._dynamo`` when the first one is built, which
costs 1.5-2.5 s per process on the reference machine: longer than the whole Ellis Island
depth-2 fit. This class calls the same fused kernel that ``torch.optim.Adam(fused=True)``
uses (``torch._fused_adam_``: one pass over each factor for the moments and the update),
and falls back to plain tensor arithmetic (the same update, about 4x slower on the
full-width factors) where a torch build lacks it. Gradients are read from ``p.grad``.
"""

from __future__ import annotations

import math
from typing import Any

import torch


class Adam:
    """Adam (Kingma & Ba) with bias correction, no weight decay; ``lr`` may change per step."""

    def __init__(
        self, params: list[torch.Tensor], lr: float, betas: tuple[float, float] = (0.9, 0.999),
        eps: float = 1e-8,
    ) -> None:
        self.params = params
        self.lr = lr
        self.beta1, self.beta2 = betas
        self.eps = eps
        self.exp_avg = [torch.zeros_like(p) for p in params]
        self.exp_avg_sq = [torch.zeros_like(p) for p in params]
        self.steps = [torch.zeros((), dtype=torch.float32, device=p.device) for p in params]
        self._fused = hasattr(torch, "_fused_adam_")
        self.lr_tensor: torch.Tensor | None = None
        """When set (see :meth:`use_lr_tensor`), the fused step reads the rate from this
        device tensor instead of ``lr``: a step recorded in a CUDA graph then follows
        :meth:`set_lr` on replay."""

    @property
    def fused(self) -> bool:
        """Whether the fused kernel is used (the fallback syncs with the host per step)."""
        return self._fused

    def use_lr_tensor(self) -> None:
        """Read the rate from a one-element tensor on the parameters' device from now on."""
        self.lr_tensor = torch.tensor(self.lr, dtype=torch.float32,
                                      device=self.params[0].device)

    def set_lr(self, lr: float) -> None:
        """Set the rate (and the rate tensor, without a host sync, when one is used)."""
        self.lr = lr
        if self.lr_tensor is not None:
            self.lr_tensor.fill_(lr)

    @torch.no_grad()
    def step(self) -> None:
        """One update of every parameter from its ``.grad``."""
        grads: list[torch.Tensor] = []
        for p in self.params:
            if p.grad is None:
                raise RuntimeError("Adam.step: every parameter needs a .grad")
            grads.append(p.grad)
        if self._fused:
            for s in self.steps:
                s.add_(1.0)
            # A float or a device tensor: _fused_adam_ has one overload for each.
            lr: Any = self.lr if self.lr_tensor is None else self.lr_tensor
            torch._fused_adam_(
                self.params, grads, self.exp_avg, self.exp_avg_sq, [], self.steps,
                lr=lr, beta1=self.beta1, beta2=self.beta2, weight_decay=0.0,
                eps=self.eps, amsgrad=False, maximize=False, grad_scale=None, found_inf=None,
            )
            return
        for p, g, m, v, s in zip(self.params, grads, self.exp_avg, self.exp_avg_sq, self.steps,
                                 strict=True):
            s.add_(1.0)
            t = float(s)
            m.lerp_(g, 1.0 - self.beta1)
            v.mul_(self.beta2).addcmul_(g, g, value=1.0 - self.beta2)
            denom = (v.sqrt() / math.sqrt(1.0 - self.beta2 ** t)).add_(self.eps)
            p.addcdiv_(m, denom, value=-self.lr / (1.0 - self.beta1 ** t))
