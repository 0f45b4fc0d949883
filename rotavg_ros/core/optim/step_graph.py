"""Replay one optimisation step as a CUDA graph, so its small kernels launch as one.

A dense DMF step is about 40 small kernels (gathers over the edges, 3x3 block products,
the factor chain, the fused Adam update). Launched one by one from Python they cost about
1 ms per step on an H100, nearly all of it launch overhead; replayed from a CUDA graph the
same kernels run back to back on the device.

The step function must be free of host syncs and must write its results into the same
tensors on every call (a graph replays fixed addresses): any per-step scalar it reads, such
as the learning rate, must live in a device tensor that is updated before each replay.
"""

from __future__ import annotations

from collections.abc import Callable

import torch


class StepGraph:
    """Call ``step`` eagerly ``eager_calls`` times, then record it once and replay it.

    ``enabled=False`` (the CPU, or CUDA graphs switched off) just calls ``step`` each time.
    The eager calls come first so that lazy set-up (cuBLAS handles, workspaces, allocator
    blocks) happens outside the capture. Capture and replay use the caller's current CUDA
    stream, and ``thread_local`` capture mode, so fits in several threads (each on its own
    stream) can record and replay their graphs side by side. A caller on the default
    stream, where capture is not allowed, gets a side stream of the graph's own for the
    eager calls, the recording and the replays (ordered after and before its own work).
    """

    def __init__(self, step: Callable[[], None], enabled: bool, eager_calls: int = 2) -> None:
        self.step = step
        self.enabled = enabled
        self.eager_calls = eager_calls
        self.calls = 0
        self.graph: torch.cuda.CUDAGraph | None = None
        self._stream: torch.cuda.Stream | None = None

    def __call__(self) -> None:
        if not self.enabled:
            self.step()
            self.calls += 1
            return
        current = torch.cuda.current_stream()
        if self._stream is None:  # capture is not allowed on the default stream
            default = current == torch.cuda.default_stream()
            self._stream = torch.cuda.Stream() if default else current
        own = self._stream
        if own != current:
            own.wait_stream(current)
        with torch.cuda.stream(own):
            if self.graph is None and self.calls >= self.eager_calls:
                self.graph = self._record()
            if self.graph is not None:
                self.graph.replay()
            else:
                self.step()
        if own != current:
            current.wait_stream(own)
        self.calls += 1

    def _record(self) -> torch.cuda.CUDAGraph:
        """Record one call of ``step`` on the current stream (nothing runs)."""
        graph = torch.cuda.CUDAGraph()
        graph.capture_begin(capture_error_mode="thread_local")
        try:
            self.step()
        finally:
            graph.capture_end()
        return graph
