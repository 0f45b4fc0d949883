"""Stress variants of the regimes (issue 14): ``python -m benchmarks.regime_stress``.

Sixty-five cases outside the record suite of :mod:`benchmarks.regimes`: eighteen drawn
with the suite's generators at parameters the suite does not use (noise between its levels,
denser or grouped false closures, a sparse random view graph, a very heavy outlier share,
dense graphs at 5 deg without false edges, short chains with 8 true loop closures and 2 or
7 false ones, the issue's new-user graph),
five graphs of kinds the suite has none of: chains in pieces that only loop closures
join (two or three sessions; a chain with dropped odometry) and a route driven three times,
whose true closures come in runs; eight planar robots (every rotation about z, noise
and false closures in heading only; on the chain, false closures from 10 deg off; five at
5 to 20 deg of heading noise, three of them clean: smallGrid3D and parking-garage at 5 deg,
torus3D at 17 deg) on the edges of suite cases; and six weighted graphs, as a
SLAM front end reports them (odometry at 0.5 deg, loop closures at 3 deg, each edge
weighted by its information ``1 / sigma^2``; :func:`~benchmarks.regime_cases.weighted_case`)
on suite topologies with false closures; and four of those measurements sent without their
weights (every weight 1, as a front end that reports no covariances sends them;
:func:`~benchmarks.regime_cases.unweighted_case`); four with noise whose level differs
from edge to edge and is not reported (lognormal about 2-5 deg;
:func:`~benchmarks.regime_cases.heteroscedastic_case`); two whose false edges are only
5-30 deg off the truth (:func:`~benchmarks.regime_cases.near_false_case`); and seven with
one to five odometry steps false, as a front end that lost its track reports them, on
chains, a revisited route and three SLAM graphs
(:func:`~benchmarks.regime_cases.broken_odometry_case`); and four of input conventions: false
closures that are the identity rotation, as a front end reports a failed match, on a chain
and on parking-garage (:func:`~benchmarks.regime_cases.identity_false_case`), torus3D with
half its edges given the other way round (:func:`~benchmarks.regime_cases.reversed_case`),
and sphere2500 at 0.1 deg of noise with 10% false closures; and a 16^3 lattice pose
graph with 10% false closures, grid3D's topology at 4,096 poses, whose sparse factors fill
in heavily (:func:`~benchmarks.regime_cases.lattice_case`); and a planar robot walking a
grid city, the Manhattan datasets' kind of graph (3,500 poses, closures at revisited
corners, 20% false, 5 deg of heading noise; :func:`~benchmarks.regime_cases.grid_walk_case`);
and three along a car's trajectory (straight runs and sharp turns,
:func:`~benchmarks.regime_cases.car_trajectory`): a 1,000-keyframe chain with 20% false
closures, a route driven twice with 30% false, and that route clean but for one wrong
odometry step (where a large step is common, the wrong one is no rare jump); and two
drone surveys, a photogrammetry view graph of mean degree 15 flown in strips, with 30%
random false matches or 20% in consistent runs of five (repetitive texture;
:func:`~benchmarks.regime_cases.survey_case`).
They look
for regimes the suite misses; a finding that holds across draws becomes a suite case
(``sfm/sparse200/out30`` came from here). Each case runs the suite's methods but the
``paper`` profile (ours, the oracle, every installed peer) as the suite does
(:func:`benchmarks.regimes.run_method`: a forked child per run, a time limit). One line per
case: ``OK`` or ``MISS`` (our median within 10% or 0.05 deg of the best peer's),
``MEAN>1.5x`` where our mean is above 1.5x the best peer's, then mean / median and time of
each method. Last, the summary (:func:`stress_summary`): the counts of those targets and of
our medians within 1.5x of the oracle's, and every variant that misses one.
``--summary F`` prints it for a run saved with ``--json F``, without running anything.

    python -m benchmarks.regime_stress [--seed 0] [--noise-model folded] [--json out.json]

``--city`` runs five variants on City10000's real topology and truth instead
(:func:`city_cases`), ``--manhattan`` five on the Manhattan world's topology
(:func:`manhattan_cases`); both need gtsam's data (the ``bench`` extra), not the shared data.

Needs the shared data (``../shared`` or ``$ROTAVG_SHARED``) otherwise; exits with a message
without it.
"""

from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Callable
from dataclasses import asdict
from pathlib import Path
from typing import Any

from benchmarks import peers
from benchmarks.datasets import find_gtsam_data, shared_dir_or_say
from benchmarks.regime_cases import (
    NOISE_MODELS,
    RegimeCase,
    broken_odometry_case,
    chain_case,
    city10000_regenerated_case,
    dense_case,
    grid_walk_case,
    heteroscedastic_case,
    identity_false_case,
    lattice_case,
    manhattan_regenerated_case,
    near_false_case,
    pieces_case,
    planar_case,
    reversed_case,
    revisit_case,
    slam_case,
    survey_case,
    unweighted_case,
    weighted_case,
)
from benchmarks.regimes import (
    ORACLE,
    OURS,
    OURS_NOFILTER,
    OURS_PAPER,
    Result,
    best_peer,
    by_case,
    methods_for,
    ok_row,
    peer_targets,
    run_method,
)


def stress_cases(shared: Path, seed: int, model: str) -> list[Callable[[], RegimeCase]]:
    """The variants, as builders (each draws its case when called)."""
    def slam(name: str, graph: str, **extra: Any) -> Callable[[], RegimeCase]:
        return lambda: slam_case(name, shared, graph, seed=seed, noise_model=model, **extra)

    def chain(name: str, nodes: int, **extra: Any) -> Callable[[], RegimeCase]:
        return lambda: chain_case(name, nodes, seed=seed, noise_model=model, **extra)

    def dense(name: str, nodes: int, degree: float, **extra: Any) -> Callable[[], RegimeCase]:
        return lambda: dense_case(name, nodes, degree, seed=seed, noise_model=model, **extra)

    def pieces(name: str, nodes: int, **extra: Any) -> Callable[[], RegimeCase]:
        return lambda: pieces_case(name, nodes, seed=seed, noise_model=model, **extra)

    def revisit(name: str, lap: int, laps: int, **extra: Any) -> Callable[[], RegimeCase]:
        return lambda: revisit_case(name, lap, laps, seed=seed, noise_model=model, **extra)

    def planar(name: str, base: Callable[[], RegimeCase], odo: float, loop: float,
               **extra: Any) -> Callable[[], RegimeCase]:
        return lambda: planar_case(name, base(), odo_noise_deg=odo, loop_noise_deg=loop,
                                   seed=seed, **extra)

    def unweighted(name: str, base: Callable[[], RegimeCase]) -> Callable[[], RegimeCase]:
        return lambda: unweighted_case(name, base(), odo_noise_deg=0.5, loop_noise_deg=3.0,
                                       seed=seed, noise_model=model)

    def weighted(name: str, base: Callable[[], RegimeCase]) -> Callable[[], RegimeCase]:
        return lambda: weighted_case(name, base(), odo_noise_deg=0.5, loop_noise_deg=3.0,
                                     seed=seed, noise_model=model)

    def hetero(name: str, base: Callable[[], RegimeCase], sigma: float
               ) -> Callable[[], RegimeCase]:
        return lambda: heteroscedastic_case(name, base(), sigma_deg=sigma, seed=seed,
                                            noise_model=model)

    def near(name: str, base: Callable[[], RegimeCase]) -> Callable[[], RegimeCase]:
        return lambda: near_false_case(name, base(), seed=seed)

    def broken(name: str, base: Callable[[], RegimeCase], steps: int
               ) -> Callable[[], RegimeCase]:
        return lambda: broken_odometry_case(name, base(), steps=steps, seed=seed)

    def identity(name: str, base: Callable[[], RegimeCase]) -> Callable[[], RegimeCase]:
        return lambda: identity_false_case(name, base())

    def flipped(name: str, base: Callable[[], RegimeCase]) -> Callable[[], RegimeCase]:
        return lambda: reversed_case(name, base(), seed=seed)

    return [
        slam("stress/torus3D/noise5", "torus3D", noise_deg=5.0),
        slam("stress/torus3D/noise10+rand5", "torus3D", noise_deg=10.0, random_false=0.05),
        slam("stress/sphere2500/noise3+rand10", "sphere2500", noise_deg=3.0,
             random_false=0.10),
        slam("stress/parking-garage/noise10", "parking-garage", noise_deg=10.0),
        slam("stress/parking-garage/noise3+grouped", "parking-garage", noise_deg=3.0,
             groups=8),
        slam("stress/smallGrid3D/noise5+rand30", "smallGrid3D", noise_deg=5.0,
             random_false=0.30),
        slam("stress/torus3D/grouped", "torus3D", groups=10),
        chain("stress/chain/500/rand30-noise3", 500, closures=30, false_random=0.30,
              odo_noise_deg=3.0, loop_noise_deg=4.0),
        chain("stress/chain/2000/grouped40", 2000, closures=60, false_grouped=0.40),
        chain("stress/chain/300/clean-noise5", 300, closures=20, odo_noise_deg=5.0,
              loop_noise_deg=5.0),
        chain("stress/chain/50/rand2", 50, closures=8, false_random=0.2),
        chain("stress/chain/50/rand7", 50, closures=8, false_random=7 / 15),
        chain("stress/chain/100/grouped7", 100, closures=8, false_grouped=7 / 15),
        pieces("stress/sessions/2x600-rand25", 1200, sessions=2, closures=40,
               false_random=0.25),
        pieces("stress/sessions/3x400-rand30", 1200, sessions=3, closures=45,
               false_random=0.30),
        pieces("stress/chain/1000/gaps3-rand25", 1000, dropped_odometry=0.03, closures=40,
               false_random=0.25),
        revisit("stress/revisit/3x400-clean", 400, 3, runs=12),
        revisit("stress/revisit/3x400-rand20", 400, 3, runs=12, false_random=0.20),
        chain("stress/car/chain/1000/rand20", 1000, closures=40, false_random=0.20,
              trajectory="car"),
        revisit("stress/car/revisit/2x400-rand30", 400, 2, runs=8, false_random=0.30,
                trajectory="car"),
        dense("stress/dense200-deg10/out30-noise3", 200, 10, outliers=0.3, noise_deg=3.0),
        dense("stress/dense400/out30-noise5", 400, 40, outliers=0.3, noise_deg=5.0),
        dense("stress/dense100/out70", 100, 50, outliers=0.7),
        dense("stress/dense400/clean-noise5", 400, 40, outliers=0.0, noise_deg=5.0),
        dense("stress/dense1000-deg30/clean-noise5", 1000, 30, outliers=0.0, noise_deg=5.0),
        planar("stress/planar/chain/1000/rand40-min10",
               chain("chain/1000/rand40", 1000, closures=36, false_random=0.40), 1.5, 2.0,
               min_false_deg=10.0),
        planar("stress/planar/parking-garage/rand5",
               slam("slam/parking-garage/rand5", "parking-garage", random_false=0.05),
               1.0, 1.0),
        planar("stress/planar/smallGrid3D/rand10",
               slam("slam/smallGrid3D/rand10", "smallGrid3D", random_false=0.10), 1.0, 1.0),
        planar("stress/planar/sphere2500/noise20",
               slam("slam/sphere2500/noise1", "sphere2500"), 20.0, 20.0),
        planar("stress/planar/parking-garage/noise10+rand10",
               slam("slam/parking-garage/rand10", "parking-garage", random_false=0.10),
               10.0, 10.0),
        planar("stress/planar/smallGrid3D/noise5",
               slam("slam/smallGrid3D/noise1", "smallGrid3D"), 5.0, 5.0),
        planar("stress/planar/parking-garage/noise5",
               slam("slam/parking-garage/noise1", "parking-garage"), 5.0, 5.0),
        planar("stress/planar/torus3D/noise17",
               slam("slam/torus3D/noise1", "torus3D"), 17.0, 17.0),
        planar("stress/planar/grid-walk/3500/noise5+rand20",
               lambda: grid_walk_case("grid-walk/3500/rand20", 3500, 30, closures=1600,
                                      false_random=0.20, seed=seed, noise_model=model),
               5.0, 5.0),
        weighted("stress/weighted/smallGrid3D/rand10",
                 slam("slam/smallGrid3D/rand10", "smallGrid3D", random_false=0.10)),
        weighted("stress/weighted/parking-garage/rand10",
                 slam("slam/parking-garage/rand10", "parking-garage", random_false=0.10)),
        weighted("stress/weighted/parking-garage/grouped",
                 slam("slam/parking-garage/grouped", "parking-garage", groups=10)),
        weighted("stress/weighted/sphere2500/rand10",
                 slam("slam/sphere2500/rand10", "sphere2500", random_false=0.10)),
        unweighted("stress/unweighted/smallGrid3D/rand10",
                   slam("slam/smallGrid3D/rand10", "smallGrid3D", random_false=0.10)),
        unweighted("stress/unweighted/parking-garage/clean",
                   slam("slam/parking-garage/noise1", "parking-garage")),
        unweighted("stress/unweighted/parking-garage/rand10",
                   slam("slam/parking-garage/rand10", "parking-garage", random_false=0.10)),
        unweighted("stress/unweighted/sphere2500/rand10",
                   slam("slam/sphere2500/rand10", "sphere2500", random_false=0.10)),
        weighted("stress/weighted/torus3D/rand10",
                 slam("slam/torus3D/rand10", "torus3D", random_false=0.10)),
        weighted("stress/weighted/chain/1000/rand30",
                 chain("chain/1000/rand30", 1000, closures=36, false_random=0.30)),
        hetero("stress/heteroscedastic/parking-garage/clean",
               slam("slam/parking-garage/noise1", "parking-garage"), 3.0),
        hetero("stress/heteroscedastic/sphere2500/rand5",
               slam("slam/sphere2500/rand5", "sphere2500", random_false=0.05), 2.0),
        hetero("stress/heteroscedastic/torus3D/clean",
               slam("slam/torus3D/noise1", "torus3D"), 5.0),
        hetero("stress/heteroscedastic/chain/1000/rand20",
               chain("chain/1000/rand20", 1000, closures=60, false_random=0.20), 2.0),
        near("stress/near/sphere2500/rand10",
             slam("slam/sphere2500/rand10", "sphere2500", random_false=0.10)),
        near("stress/near/chain/1000/rand30",
             chain("chain/1000/rand30", 1000, closures=60, false_random=0.30)),
        broken("stress/odometry-breaks/chain/1000/clean",
               chain("chain/1000/clean", 1000, closures=36), 2),
        broken("stress/odometry-breaks/chain/1000/rand30",
               chain("chain/1000/rand30", 1000, closures=36, false_random=0.30), 2),
        broken("stress/odometry-breaks/chain/300/rand20",
               chain("chain/300/rand20", 300, closures=12, false_random=0.20), 1),
        broken("stress/odometry-breaks/revisit/3x400-rand20",
               revisit("revisit/3x400-rand20", 400, 3, runs=12, false_random=0.20), 3),
        broken("stress/odometry-breaks/parking-garage/rand5",
               slam("slam/parking-garage/rand5", "parking-garage", random_false=0.05), 3),
        broken("stress/odometry-breaks/sphere2500/rand10",
               slam("slam/sphere2500/rand10", "sphere2500", random_false=0.10), 5),
        broken("stress/odometry-breaks/torus3D/clean",
               slam("slam/torus3D/noise1", "torus3D"), 5),
        broken("stress/odometry-breaks/car/revisit/2x400-clean",
               revisit("revisit/car/2x400", 400, 2, runs=8, trajectory="car"), 1),
        identity("stress/identity/chain/1000/rand30",
                 chain("chain/1000/rand30", 1000, closures=36, false_random=0.30)),
        identity("stress/identity/parking-garage/rand10",
                 slam("slam/parking-garage/rand10", "parking-garage", random_false=0.10)),
        flipped("stress/reversed/torus3D/rand10",
                slam("slam/torus3D/rand10", "torus3D", random_false=0.10)),
        slam("stress/sphere2500/noise0.1+rand10", "sphere2500", noise_deg=0.1,
             random_false=0.10),
        lambda: lattice_case("stress/lattice/16/rand10", 16, random_false=0.10, seed=seed,
                             noise_model=model),
        lambda: survey_case("stress/survey/12x60/rand30", 12, 60, false=0.30, seed=seed,
                            noise_model=model),
        lambda: survey_case("stress/survey/12x60/grouped20", 12, 60, false=0.20,
                            grouped=True, seed=seed, noise_model=model),
    ]


def verdict(ours: Result, rows: list[Result]) -> str:
    """``OK`` / ``MISS`` against the best peer's median, and ``MEAN>1.5x`` (or '')."""
    targets = peer_targets(ours, rows) if ours.status == "ok" else None
    if targets is None:
        return "-"
    return ("OK" if targets[0] else "MISS") + (" MEAN>1.5x" if targets[1] else "")


def stress_summary(results: list[Result]) -> list[str]:
    """The summary of a stress run: one line with the counts of issue 14's two per-case
    targets against the best peer (:func:`~benchmarks.regimes.peer_targets`) and of our
    medians within 1.5x of the oracle's, then one line per variant that misses any of them.
    Variants where ours failed or no peer ran are counted in neither."""
    within = worse_mean = compared = near_oracle = with_oracle = 0
    misses: list[str] = []
    for name, rows in by_case(results).items():
        ours = ok_row(rows, OURS)
        if ours is None:
            continue
        oracle = ok_row(rows, ORACLE)
        if oracle is not None:
            with_oracle += 1
            if ours.median_deg <= 1.5 * oracle.median_deg:
                near_oracle += 1
            else:
                misses.append(f"  beyond 1.5x the oracle: {name}: {ours.median_deg:.3f} "
                              f"against {oracle.median_deg:.3f} median")
        targets = peer_targets(ours, rows)
        if targets is None:
            continue
        compared += 1
        within += targets[0]
        worse_mean += targets[1]
        if not targets[0] or targets[1]:
            misses.append(f"  {verdict(ours, rows)}: {name}: ours "
                          f"{ours.mean_deg:.3f} / {ours.median_deg:.3f}, best peer mean "
                          f"{best_of(rows, 'mean_deg'):.3f}, median "
                          f"{best_of(rows, 'median_deg'):.3f}")
    return [f"Summary (ours): median within 10% (or 0.05 deg) of the best peer's on "
            f"{within} / {compared} variants; mean above 1.5x the best peer's on "
            f"{worse_mean} / {compared}; median within 1.5x of the oracle's on "
            f"{near_oracle} / {with_oracle}", *misses]


def best_of(rows: list[Result], key: str) -> float:
    """The best peer's ``key`` among a variant's ``rows`` (NaN where no peer ran)."""
    best = best_peer(rows, key)
    return float("nan") if best is None else float(getattr(best, key))


def read_results(path: str) -> list[Result]:
    """The results :func:`write_results` saved."""
    return [Result(**row) for row in json.loads(Path(path).read_text())]


def result_cells(rows: list[Result]) -> str:
    """Each method's ``mean/median time`` (or its status), as one line's cells."""
    return " | ".join(f"{r.method} {r.mean_deg:.3f}/{r.median_deg:.3f} {r.wall_s:.2f}s"
                      if r.status == "ok" else f"{r.method} {r.status}" for r in rows)


def write_results(path: str, results: list[Result]) -> None:
    """The raw results as JSON, without the per-node errors."""
    Path(path).write_text(json.dumps([{**asdict(r), "errors": None} for r in results],
                                     indent=1))


def city_cases(data: Path, seed: int) -> list[Callable[[], RegimeCase]]:
    """``--city``: five variants on City10000's real topology and ground truth, headings
    regenerated (:func:`~benchmarks.regime_cases.city10000_regenerated_case`; the noise is
    about z only, so every noise model draws the same): clean at 5 and 10 deg, 10% random
    false closures at 2 deg, 20 runs of grouped false closures at 1 deg, and both (20%
    random, 10 runs) at 3 deg. 10,000 poses each: about two minutes a variant with the
    peers."""
    def city(name: str, **extra: Any) -> Callable[[], RegimeCase]:
        return lambda: city10000_regenerated_case(name, data, seed=seed, **extra)

    return [
        city("stress/city10000/noise5", noise_deg=5.0),
        city("stress/city10000/noise10", noise_deg=10.0),
        city("stress/city10000/noise2+rand10", noise_deg=2.0, random_false=0.10),
        city("stress/city10000/noise1+grouped20", noise_deg=1.0, groups=20),
        city("stress/city10000/noise3+rand20+grouped10", noise_deg=3.0, random_false=0.20,
             groups=10),
    ]


def manhattan_cases(data: Path, seed: int) -> list[Callable[[], RegimeCase]]:
    """``--manhattan``: the Manhattan world's real topology (10,000 poses, 54,312 loop
    closures: mean degree 12.9), its file's headings as the truth
    (:func:`~benchmarks.regime_cases.manhattan_regenerated_case`): clean at 5 deg, 10%
    random false closures at 2 deg, 20 runs of grouped false closures at 1 deg, both (20%
    random, 10 runs) at 3 deg, and 20% random at 5 deg (the synthetic grid walk's regime).
    About three minutes a variant with the peers."""
    def manhattan(name: str, **extra: Any) -> Callable[[], RegimeCase]:
        return lambda: manhattan_regenerated_case(name, data, seed=seed, **extra)

    return [
        manhattan("stress/manhattan/noise5", noise_deg=5.0),
        manhattan("stress/manhattan/noise2+rand10", noise_deg=2.0, random_false=0.10),
        manhattan("stress/manhattan/noise1+grouped20", noise_deg=1.0, groups=20),
        manhattan("stress/manhattan/noise3+rand20+grouped10", noise_deg=3.0,
                  random_false=0.20, groups=10),
        manhattan("stress/manhattan/noise5+rand20", noise_deg=5.0, random_false=0.20),
    ]


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--noise-model", choices=NOISE_MODELS, default="folded")
    p.add_argument("--timeout", type=float, default=300.0, help="per case and method, s")
    p.add_argument("--json", help="write the raw results (no per-node errors) here")
    p.add_argument("--cases", help="comma-separated substrings of the variants' names")
    p.add_argument("--summary", metavar="JSON",
                   help="print the summary of a run saved with --json, and run nothing")
    topology = p.add_mutually_exclusive_group()
    topology.add_argument("--city", action="store_true",
                          help="run the five City10000 variants instead (needs gtsam's data)")
    topology.add_argument("--manhattan", action="store_true",
                          help="run the five Manhattan world variants instead (needs gtsam's "
                               "data)")
    args = p.parse_args()
    if args.summary:
        print("\n".join(stress_summary(read_results(args.summary))))
        return 0
    wanted = args.cases.split(",") if args.cases else [""]
    available = peers.available_peers()
    results: list[Result] = []
    if args.city or args.manhattan:
        data = find_gtsam_data()  # gtsam's data only, no shared data needed
        if data is None:
            print(f"regime_stress --{'city' if args.city else 'manhattan'}: gtsam's data "
                  "folder not found; install the bench extra (requirements-bench.txt)")
            return 0
        builders = (city_cases if args.city else manhattan_cases)(data, args.seed)
    else:
        shared = shared_dir_or_say("regime_stress")
        if shared is None:
            return 0
        builders = stress_cases(shared, args.seed, args.noise_model)
    for build in builders:
        case = build()
        if not any(part in case.name for part in wanted):
            continue
        rows = [run_method(case, method, args.timeout)
                for method, runnable in methods_for(case, available)
                if runnable and method not in (OURS_PAPER, OURS_NOFILTER)]
        results += rows
        print(f"{verdict(rows[0], rows):14s} {case.name:36s} {result_cells(rows)}", flush=True)
    print("\n".join(stress_summary(results)))
    if args.json:
        write_results(args.json, results)
    return 0


if __name__ == "__main__":
    sys.exit(main())
