"""Regime benchmark (issue 14, deliverable 1): ``python -m benchmarks.regimes``.

Runs every case of :mod:`benchmarks.regime_cases` (SLAM topologies with regenerated
measurements, plain odometry chains, Ellis Island and dense synthetic graphs, the SE-Sync
graphs as measured) with our solver and the installed peers in the same run, and scores each
against ground truth after gauge alignment (:func:`rotavg_ros.core.metrics.evaluate`):
mean, median and 95th-percentile angular error in degrees, plus wall time.

Methods: ``ours`` (default profile), ``ours-paper`` (``paper`` profile), ``ours-nofilter``
(``use_filter=False``; only when asked for with ``--methods``), ``oracle``
(ours, default options, on the true edges only; generated cases), GTSAM chordal, GTSAM
Shonan+Huber, pycolmap L1/2 (HALF_NORM), GTSAM GNC-TLS from the chordal start, and GNC-TLS
with the odometry edges (``|i - j| == 1``) as known inliers where a case has odometry.
GNC-TLS's sigma is the case's ``sigma_deg`` (see :class:`~benchmarks.regime_cases.RegimeCase`).

Isolation: every (case, method) runs in a **forked** child process with a time
limit (``--timeout``, default 120 s; a run past it is killed and reported as ``timeout``).
The parent imports torch, gtsam and pycolmap once but runs no solver, so each child starts
clean without paying the imports again. Times are each method's own solve call (for GNC-TLS
and Shonan the chordal start is not timed, as in :mod:`benchmarks.peers`; for ours the whole
``RotationAverager.solve``). Our solver runs on the CPU (CUDA hidden from the child) unless
``--device cuda`` is given; the peers always run on the CPU.

Summary (issue 14 targets): the count of cases where our median is within 10% (or 0.05 deg)
of the best peer's median, the count where our mean exceeds 1.5x the best peer's mean,
for generated cases the ratio of our median to the oracle's, and on the SLAM and chain cases
with false closures our median and time against the better GNC-TLS variant's.
"""

from __future__ import annotations

import argparse
import fnmatch
import json
import multiprocessing as mp
import os
import sys
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from benchmarks import peers
from benchmarks.datasets import find_gtsam_data, shared_dir_or_say
from benchmarks.regime_cases import FAMILIES, NOISE_MODELS, QUICK, RegimeCase, all_cases
from rotavg_ros.core.metrics import evaluate
from rotavg_ros.core.options import SolverOptions
from rotavg_ros.core.solver import RotationAverager

OURS = "ours"
OURS_PAPER = "ours-paper"
OURS_NOFILTER = "ours-nofilter"
ORACLE = "oracle"
GNC_ODO = "gtsam_gnc_tls+odo"
PEER_METHODS = ("gtsam_chordal", "gtsam_shonan_huber", "pycolmap_half_norm",
                "gtsam_gnc_tls", GNC_ODO)
METHODS = (OURS, OURS_PAPER, OURS_NOFILTER, ORACLE, *PEER_METHODS)


def our_options(profile: str = "default", **flat: Any) -> SolverOptions:
    """Our solver options: a profile, then flat names (``use_filter=False``, ``seed=0``)."""
    return SolverOptions.for_profile(profile, **flat)


@dataclass
class Result:
    """One (case, method) run. ``status``: ok, error, timeout, not installed."""

    case: str
    family: str
    nodes: int
    edges: int
    method: str
    status: str
    mean_deg: float = float("nan")
    median_deg: float = float("nan")
    p95_deg: float = float("nan")
    wall_s: float = float("nan")
    note: str = ""
    errors: list[float] | None = field(default=None, repr=False)
    false_edges: int = 0
    """Edges the case made false on purpose (false loop closures, outliers)."""


# ------------------------------------------------------------------------ running


def solve_ours(case: RegimeCase, keep: np.ndarray | None, flat: dict[str, Any],
               profile: str = "default") -> tuple[np.ndarray, float, str]:
    """Our solver in this process on ``case`` (its edges ``keep``, default all), with the
    ``profile`` and flat options: ``(world-to-node rotations in case order, solve wall time
    s, note)``."""
    g = case.view_graph(keep)
    t0 = time.perf_counter()
    res = RotationAverager(our_options(profile, **flat)).solve(g)
    wall = time.perf_counter() - t0
    rot = np.stack([res.rotations[g.index_of(k)] for k in range(case.num_nodes)])
    note = f"depth {res.depth}, {res.num_filtered} filtered"
    if res.verification:
        note += (f"; kept {res.verification}, noise {res.noise_sigma_deg:.2f} deg, "
                 f"{res.num_rejected_verify} rejected, {res.num_readmitted} re-admitted")
        if res.num_relocalized:
            note += f", {res.num_relocalized} relocalized"
        if res.num_trusted_odometry:
            note += f", {res.num_trusted_odometry} odometry trusted"
        if res.num_runs_left_out:
            note += f", {res.num_runs_left_out} closure runs left out"
        if res.odometry_bias_deg_per_step:
            note += f", odometry bias {res.odometry_bias_deg_per_step:.3f} deg a step removed"
    return rot, wall, note


def _solve(case: RegimeCase, method: str, device: str) -> tuple[np.ndarray, float, str]:
    ours = {"seed": 0, "device": device}
    if method == OURS:
        return solve_ours(case, None, ours)
    if method == OURS_PAPER:
        return solve_ours(case, None, ours, profile="paper")
    if method == OURS_NOFILTER:
        return solve_ours(case, None, {**ours, "use_filter": False})
    if method == ORACLE:
        return solve_ours(case, case.inlier, ours)
    sigma = float(np.radians(case.sigma_deg))
    if method == "gtsam_gnc_tls":
        rot, wall = peers.run_gtsam_gnc_tls(case.num_nodes, case.i, case.j, case.R,
                                            case.weight, sigma=sigma)
        return rot, wall, f"sigma {case.sigma_deg:.3g} deg"
    if method == GNC_ODO:
        odo = np.flatnonzero(case.odometry)
        rot, wall = peers.run_gtsam_gnc_tls(case.num_nodes, case.i, case.j, case.R,
                                            case.weight, sigma=sigma, known_inliers=odo)
        return rot, wall, f"sigma {case.sigma_deg:.3g} deg, {odo.size} known inliers"
    rot, wall = peers.PEERS[method](case.num_nodes, case.i, case.j, case.R, case.weight)
    return rot, wall, ""


def _child(case: RegimeCase, method: str, device: str, q: Any) -> None:
    if device == "cpu":
        os.environ["CUDA_VISIBLE_DEVICES"] = ""
    try:
        rot, wall, note = _solve(case, method, device)
        q.put(("ok", rot, wall, note))
    except Exception as exc:  # a row, the benchmark goes on
        q.put(("error", None, 0.0, f"{type(exc).__name__}: {exc}"[:200]))


def run_method(case: RegimeCase, method: str, timeout: float,
               start_method: str = "fork", device: str = "cpu") -> Result:
    """Run one method on ``case`` in a child process and score it.

    ``fork`` (the benchmark's choice: no re-import per run) is safe only from a process that
    has started no thread pools yet and has not initialised CUDA; a process that has (a test
    session that ran torch) passes ``spawn``. ``device`` is our solver's (``cpu`` or
    ``cuda``); the peers ignore it.
    """
    false = 0 if case.inlier is None else int(np.count_nonzero(~case.inlier))
    base: dict[str, Any] = dict(case=case.name, family=case.family, nodes=case.num_nodes,
                                edges=case.num_edges, method=method, false_edges=false)
    ctx: Any = mp.get_context(start_method)
    q = ctx.Queue()
    proc = ctx.Process(target=_child, args=(case, method, device, q))
    proc.start()
    try:
        status, rot, wall, note = q.get(timeout=timeout)
    except Exception:
        proc.kill()
        proc.join()
        return Result(**base, status="timeout", note=f"killed after {timeout:.0f} s")
    proc.join()
    if status != "ok":
        return Result(**base, status="error", note=note)
    stats = evaluate(dict(enumerate(rot)), dict(enumerate(case.gt)))
    err = stats.errors
    return Result(**base, status="ok", mean_deg=stats.mean_deg, median_deg=stats.median_deg,
                  p95_deg=float(np.percentile(err, 95)), wall_s=float(wall), note=note,
                  errors=err.tolist())


def methods_for(case: RegimeCase, available: dict[str, bool]) -> list[tuple[str, bool]]:
    """``(method, runnable)`` for this case (oracle only with a known inlier set, GNC
    with known inliers only with odometry)."""
    out: list[tuple[str, bool]] = [(OURS, True), (OURS_PAPER, True), (OURS_NOFILTER, True)]
    if case.inlier is not None:
        out.append((ORACLE, True))
    for m in PEER_METHODS:
        if m == GNC_ODO and not case.has_odometry:
            continue
        out.append((m, available.get("gtsam_gnc_tls" if m == GNC_ODO else m, False)))
    return out


# ------------------------------------------------------------------------ reporting


def _num(x: float) -> str:
    return "–" if not np.isfinite(x) else (f"{x:.3f}" if x < 100 else f"{x:.1f}")


HEADER = ["| case | family | N | E | method | mean ° | median ° | p95 ° | time s | note |",
          "|---|---|---|---|---|---|---|---|---|---|"]


def format_row(r: Result) -> str:
    note = r.note if r.status == "ok" else f"{r.status}: {r.note}".rstrip(": ")
    note = note.replace("|", "/")
    return (f"| {r.case} | {r.family} | {r.nodes} | {r.edges} | {r.method} | "
            f"{_num(r.mean_deg)} | {_num(r.median_deg)} | {_num(r.p95_deg)} | "
            f"{_num(r.wall_s)} | {note} |")


def best_peer(rows: list[Result], key: str) -> Result | None:
    ok = [r for r in rows if r.method in PEER_METHODS and r.status == "ok"]
    return min(ok, key=lambda r: getattr(r, key)) if ok else None


def by_case(results: list[Result]) -> dict[str, list[Result]]:
    """The results grouped by case, in the order the cases ran."""
    grouped: dict[str, list[Result]] = {}
    for r in results:
        grouped.setdefault(r.case, []).append(r)
    return grouped


def ok_row(rows: list[Result], method: str) -> Result | None:
    """``method``'s row among a case's ``rows`` where it ran to the end, else None."""
    return next((r for r in rows if r.method == method and r.status == "ok"), None)


def peer_targets(ours: Result, rows: list[Result]) -> tuple[bool, bool] | None:
    """Issue 14's two per-case targets for ``ours`` among a case's ``rows``: (median within
    10% or 0.05 deg of the best peer's median, mean above 1.5x the best peer's mean); None
    where no peer ran."""
    bm, bmean = best_peer(rows, "median_deg"), best_peer(rows, "mean_deg")
    if bm is None or bmean is None:
        return None
    return (ours.median_deg <= max(1.1 * bm.median_deg, bm.median_deg + 0.05),
            ours.mean_deg > 1.5 * bmean.mean_deg)


def summarize(results: list[Result], method: str = OURS) -> str:
    """The issue's target counts and oracle ratios of ``method``, as markdown."""
    cases = by_case(results)
    within = worse_mean = compared = 0
    far: list[str] = []
    ratios: list[str] = []
    ratio_vals: list[float] = []
    for name, rows in cases.items():
        ours = ok_row(rows, method)
        bm, bmean = best_peer(rows, "median_deg"), best_peer(rows, "mean_deg")
        oracle = ok_row(rows, ORACLE)
        if ours is not None and oracle is not None:
            ratio = ours.median_deg / max(oracle.median_deg, 1e-12)
            ratio_vals.append(ratio)
            ratios.append(f"| {name} | {ours.median_deg:.3f} | {oracle.median_deg:.3f} | "
                          f"{ratio:.2f} |")
        targets = None if ours is None else peer_targets(ours, rows)
        if ours is None or bm is None or bmean is None or targets is None:
            continue
        compared += 1
        within += targets[0]
        if targets[1]:
            worse_mean += 1
            far.append(f"| {name} | {ours.mean_deg:.3f} / {ours.median_deg:.3f} | "
                       f"{bmean.method}: {bmean.mean_deg:.3f} | "
                       f"{bm.method}: {bm.median_deg:.3f} |")
    out = [f"**Summary ({method}):** within 10% (or 0.05°) of the best peer's median on "
           f"{within}/{compared} cases; our mean > 1.5× the best peer's mean on "
           f"{worse_mean}/{compared} cases; ours/oracle median ratio over "
           f"{len(ratio_vals)} generated cases: median "
           f"{np.median(ratio_vals) if ratio_vals else float('nan'):.2f}, "
           f"{sum(v <= 1.5 for v in ratio_vals)} within 1.5×."]
    out += gnc_comparison(cases, method)
    if far:
        out += ["", "Cases where our mean is more than 1.5× the best peer's mean:", "",
                "| case | ours mean / median ° | best peer mean ° | best peer median ° |",
                "|---|---|---|---|", *far]
    if ratios:
        out += ["", "| case | ours median ° | oracle median ° | ratio |", "|---|---|---|---|",
                *ratios]
    return "\n".join(out)


EQUAL_MEDIANS = 0.005
"""Two medians within this fraction of the GNC-TLS one count as equal (the same inlier
set solved by two estimators)."""


def gnc_comparison(cases: dict[str, list[Result]], method: str = OURS) -> list[str]:
    """Issue 14's GNC target on the SLAM and chain cases with false closures: ``method``'s
    median against the better GNC-TLS variant's (the lower median), and its time against
    a quarter of that variant's; a summary line and a table (markdown lines)."""
    rows: list[str] = []
    lower = equal = quick = 0
    for name, case_rows in cases.items():
        ours = ok_row(case_rows, method)
        gnc = [r for r in case_rows if r.method in ("gtsam_gnc_tls", GNC_ODO)
               and r.status == "ok"]
        if ours is None or not gnc or ours.family not in ("slam", "chain") \
                or ours.false_edges == 0:
            continue
        best = min(gnc, key=lambda r: (r.median_deg, r.wall_s))
        if abs(ours.median_deg - best.median_deg) <= EQUAL_MEDIANS * best.median_deg:
            equal += 1
        else:
            lower += ours.median_deg < best.median_deg
        quick += ours.wall_s <= 0.25 * best.wall_s
        rows.append(f"| {name} | {ours.median_deg:.3f} | {best.method}: "
                    f"{best.median_deg:.3f} | {ours.wall_s:.2f} | {best.wall_s:.2f} | "
                    f"{ours.wall_s / max(best.wall_s, 1e-9):.2f} |")
    if not rows:
        return []
    n = len(rows)
    return ["", f"**Against GNC-TLS ({method}),** SLAM and chain cases with false closures: "
            f"median lower than the better variant's on {lower}/{n}, equal (within "
            f"{EQUAL_MEDIANS:.1%}) on {equal}/{n}, higher on {n - lower - equal}/{n}; time "
            f"at most a quarter of its time on {quick}/{n}.", "",
            "| case | ours median ° | better GNC-TLS median ° | ours s | GNC-TLS s | "
            "time ratio |", "|---|---|---|---|---|---|", *rows]


def write_plots(results: list[Result], folder: Path) -> list[Path]:
    """One error-CDF figure per regime family (a panel per case, a line per method)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    folder.mkdir(parents=True, exist_ok=True)
    written = []
    for family in FAMILIES:
        cases = list(dict.fromkeys(r.case for r in results if r.family == family))
        if not cases:
            continue
        cols = min(4, len(cases))
        rows = (len(cases) + cols - 1) // cols
        fig, axes = plt.subplots(rows, cols, figsize=(4 * cols, 3 * rows), squeeze=False)
        for ax, name in zip(axes.flat, cases, strict=False):
            for r in results:
                if r.case == name and r.errors:
                    e = np.sort(np.maximum(np.asarray(r.errors), 1e-4))
                    ax.plot(e, np.arange(1, e.size + 1) / e.size, label=r.method,
                            lw=2 if r.method == OURS else 1)
            ax.set_xscale("log")
            ax.set_title(name, fontsize=8)
            ax.set_xlabel("error (deg)", fontsize=7)
            ax.tick_params(labelsize=6)
        for ax in list(axes.flat)[len(cases):]:
            ax.axis("off")
        axes.flat[0].legend(fontsize=6)
        fig.tight_layout()
        path = folder / f"cdf_{family}.png"
        fig.savefig(path, dpi=100)
        plt.close(fig)
        written.append(path)
    return written


# ------------------------------------------------------------------------ main


def select(names: list[str], patterns: str | None, quick: bool) -> list[str]:
    """Case names matching any comma-separated glob (or substring) in ``patterns``."""
    if quick:
        names = [n for n in names if n in QUICK]
    if not patterns:
        return names
    pats = [p.strip() for p in patterns.split(",") if p.strip()]
    return [n for n in names if any(fnmatch.fnmatch(n, p) or p in n for p in pats)]


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m benchmarks.regimes", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--cases", help="comma-separated globs or substrings of case names")
    p.add_argument("--quick", action="store_true", help="a small fast subset")
    p.add_argument("--list", action="store_true", help="list the cases and exit")
    p.add_argument("--methods", help="comma-separated subset of: " + ", ".join(METHODS)
                   + f" (default: all but {OURS_NOFILTER})")
    p.add_argument("--timeout", type=float, default=120.0, help="per case and method, s")
    p.add_argument("--markdown", help="also write the table and summary to this file")
    p.add_argument("--json", help="write the raw results (per-node errors too) here")
    p.add_argument("--plots", help="folder for one error-CDF PNG per family (matplotlib)")
    p.add_argument("--seed", type=int, default=0,
                   help="draw the generated cases with this seed (default 0: the record)")
    p.add_argument("--noise-model", choices=NOISE_MODELS, default="folded",
                   help="measurement noise of the generated cases (default folded: the record)")
    p.add_argument("--device", choices=("cpu", "cuda"), default="cpu",
                   help="our solver's device (default cpu; the peers always run on the CPU)")
    args = p.parse_args(argv)
    builders = all_cases(args.seed, args.noise_model)
    if find_gtsam_data() is None:
        print("regimes: gtsam's data folder not found (the bench extra): the City10000 cases "
              "are left out", file=sys.stderr)
    names = select(list(builders), args.cases, args.quick)
    if args.list:
        for n in names:
            print(n)
        return 0
    shared = shared_dir_or_say("regimes")
    if shared is None:
        return 0
    default = [m for m in METHODS if m != OURS_NOFILTER]
    wanted = set(default if not args.methods else args.methods.split(","))
    unknown = wanted - set(METHODS)
    if unknown:
        p.error(f"unknown methods: {', '.join(sorted(unknown))}")
    available = peers.available_peers()
    for mod in ("gtsam", "pycolmap"):  # import once in the parent; children fork
        peers._has_module(mod)
    results: list[Result] = []
    t_start = time.perf_counter()
    print("\n".join(HEADER), flush=True)
    for name in names:
        case = builders[name](shared)
        for method, runnable in methods_for(case, available):
            if method not in wanted:
                continue
            if not runnable:
                r = Result(case.name, case.family, case.num_nodes, case.num_edges, method,
                           "not installed")
            else:
                r = run_method(case, method, args.timeout, device=args.device)
            results.append(r)
            print(format_row(r), flush=True)
    total = time.perf_counter() - t_start
    table = "\n".join([*HEADER, *(format_row(r) for r in results)])
    summary = summarize(results)
    if any(r.method == OURS_PAPER for r in results):
        summary += "\n\n" + summarize(results, OURS_PAPER).split("\n")[0]
    draw = f"seed {args.seed}, {args.noise_model} noise, ours on {args.device}"
    print(f"\n{summary}\n\ntotal wall time {total:.0f} s for {len(names)} cases ({draw})",
          flush=True)
    if args.markdown:
        Path(args.markdown).write_text(
            f"{table}\n\n{summary}\n\ntotal wall time {total:.0f} s for {len(names)} cases "
            f"({draw})\n")
    if args.json:
        Path(args.json).write_text(json.dumps([asdict(r) for r in results]))
    if args.plots:
        for path in write_plots(results, Path(args.plots)):
            print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
