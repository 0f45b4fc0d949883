"""Odometry with a systematic bias (issue 14): ``python -m benchmarks.odometry_bias``.

Every other generator draws the odometry's error afresh each step, so loop errors grow
with the square root of the path, as the solver's loop tests assume. A gyro's yaw bias
turns every step the same way, and the loop errors grow linearly instead. Here each
odometry measurement is turned ``--biases`` degrees further about its frame's z axis
(:func:`~benchmarks.regime_cases.biased_odometry_case`) on the suite's chains (300
keyframes with 20% false closures, 1,000 with 40% and clean, 3,000 with 35% random and
grouped), with the odometry at 1.5 deg (the suite's) or ``--odometry-noise``, and, where
the shared data is there, on parking-garage and sphere2500 with 5% false closures. Ours
(default profile) and the oracle (the same on the true edges, biased odometry included)
run in process; ``--peers`` adds GTSAM chordal and GNC-TLS, plain and with the odometry
as known inliers (each in a child process, as :mod:`benchmarks.regimes` runs them). One
line per graph, flagged where our mean or median is more than 1.5x the oracle's; the
summary counts them.

    python -m benchmarks.odometry_bias [--seeds 0-2] [--biases 0.05,0.2,0.5,1] [--peers]
"""

from __future__ import annotations

import argparse
import functools
import sys
from collections.abc import Callable, Iterator

from benchmarks.datasets import find_shared_dir
from benchmarks.regime_cases import RegimeCase, biased_odometry_case, chain_case, slam_case
from benchmarks.short_chains import PEERS, seed_range, solve

CHAINS = (("chain/300/rand20", 300, 16, 0.20, 0.0), ("chain/1000/rand40", 1000, 36, 0.40, 0.0),
          ("chain/1000/clean", 1000, 36, 0.0, 0.0), ("chain/3000/mixed35", 3000, 100, 0.15, 0.20))
"""The suite's chains (:func:`benchmarks.regime_cases.all_cases`) and a clean one: name,
keyframes, true closures, random and grouped false shares."""
SLAM = (("slam/parking-garage/rand5", "parking-garage"), ("slam/sphere2500/rand5", "sphere2500"))


def bases(seed: int, odometry_noise: float, slam: bool) -> Iterator[Callable[[], RegimeCase]]:
    """The unbiased graphs of one draw, as builders."""
    for name, nodes, closures, random, grouped in CHAINS:
        yield functools.partial(chain_case, name, nodes, closures=closures,
                                false_random=random, false_grouped=grouped, seed=seed,
                                odo_noise_deg=odometry_noise)
    shared = find_shared_dir() if slam else None
    if shared is not None:
        for name, graph in SLAM:
            yield functools.partial(slam_case, name, shared, graph, random_false=0.05,
                                    seed=seed)


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--seeds", default="0-2", help="draws, e.g. 0-2 (default) or 5")
    p.add_argument("--biases", default="0.05,0.2,0.5,1",
                   help="odometry bias per step, deg, comma-separated")
    p.add_argument("--odometry-noise", type=float, default=1.5,
                   help="odometry noise per step of the chains, deg (default 1.5)")
    p.add_argument("--no-slam", action="store_true", help="chains only")
    p.add_argument("--peers", action="store_true", help="also GTSAM chordal and GNC-TLS")
    args = p.parse_args()
    biases = [float(b) for b in args.biases.split(",")]
    if not args.no_slam and find_shared_dir() is None:
        print("shared data not found (../shared or $ROTAVG_SHARED): chains only")
    total = off_median = off_mean = 0
    for seed in seed_range(args.seeds):
        for build in bases(seed, args.odometry_noise, not args.no_slam):
            base = build()
            for bias in biases:
                case = biased_odometry_case(f"{base.name}/bias{bias:g}", base, bias_deg=bias)
                row = solve(case, args.peers)
                total += 1
                bad_median = row.ours[1] > 1.5 * row.oracle[1]
                bad_mean = row.ours[0] > 1.5 * row.oracle[0]
                off_median += bad_median
                off_mean += bad_mean
                line = (f"{case.name:34s} draw {seed}: ours {row.ours[0]:7.2f} / "
                        f"{row.ours[1]:7.2f} ({row.ours[2]:.2f} s), oracle "
                        f"{row.oracle[0]:6.2f} / {row.oracle[1]:6.2f}")
                for m in PEERS:
                    if m in row.peers:
                        line += f", {m} {row.peers[m][0]:.2f} / {row.peers[m][1]:.2f}"
                print(line + ("  >1.5x oracle" if bad_median else "")
                      + ("  mean >1.5x oracle" if bad_mean else "") + f"  | {row.note}",
                      flush=True)
    print(f"\n{total} graphs: our median more than 1.5x the oracle's on {off_median}, our "
          f"mean on {off_mean}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
