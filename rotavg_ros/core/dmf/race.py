"""Early elimination of the depth candidates that have clearly lost (beyond the paper).

The candidates of one solve fit in parallel threads. One of them, the pace-setter (the
solver takes the shallowest depth: the cheapest fit, and from a near-zero start the
fastest learner), runs freely and reports the cost it is chosen by (Eq. 3, computed by the
solver) at fixed iteration checkpoints. Every other candidate, at the same checkpoint,
waits for the pace-setter's report and stops when its own cost is clearly higher.

The decisions depend only on costs, never on thread timing. The pace-setter waits for
nobody, so a schedule that starts it first (the solver submits it first to its FIFO thread
pool) cannot deadlock, whatever the number of worker threads.
"""

from __future__ import annotations

import math
import threading


class CandidateRace:
    """Shared, thread-safe state of one race between candidates (e.g. DMF depths).

    At a checkpoint ``step``, a candidate other than ``pacer`` stops when its cost exceeds
    ``(1 + ratio)`` times the pace-setter's cost at the same step: its report, or its final
    cost (given to :meth:`finish`) once it has ended before ``step``. A failed pace-setter
    or a non-finite cost stops nobody.
    """

    def __init__(self, pacer: int, ratio: float) -> None:
        self.pacer = pacer
        self.ratio = ratio
        self.stopped: dict[int, int] = {}
        """Stopped candidates and the checkpoint at which they stopped."""
        self._cond = threading.Condition()
        self._costs: dict[int, float] = {}
        self._final: float | None = None
        self._ended = False

    def report(self, key: int, step: int, cost: float) -> bool:
        """Record ``key``'s cost at checkpoint ``step``; True when ``key`` must stop now.

        A candidate other than the pace-setter blocks until the pace-setter has reported
        ``step`` or ended.
        """
        with self._cond:
            if key == self.pacer:
                self._costs[step] = cost
                self._cond.notify_all()
                return False
            self._cond.wait_for(lambda: step in self._costs or self._ended)
            ref = self._costs.get(step, self._final)
            if ref is not None and math.isfinite(ref) and cost > (1.0 + self.ratio) * ref:
                self.stopped[key] = step
                return True
            return False

    def finish(self, key: int, cost: float | None) -> None:
        """``key`` ended, with final cost ``cost`` (None: it failed). Call it exactly once
        for the pace-setter, also when it fails, or the others wait for ever."""
        if key != self.pacer:
            return
        with self._cond:
            self._ended, self._final = True, cost
            self._cond.notify_all()
