"""``rotavg bench ...``: the benchmarks of the source checkout (``benchmarks/``).

The benchmarks and their peers are not installed with the node; this command finds them next
to the package in a source checkout (``pip install -e .``) and runs ``benchmarks.paper``.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from rotavg_ros.errors import InputError

CHECKOUT = Path(__file__).resolve().parents[2]


def cmd_bench(args: argparse.Namespace) -> int:
    if not (CHECKOUT / "benchmarks" / "paper.py").is_file():
        raise InputError("rotavg bench needs the source checkout (benchmarks/ is not "
                         "installed); run `python -m benchmarks.paper` there")
    if str(CHECKOUT) not in sys.path:
        sys.path.insert(0, str(CHECKOUT))
    from benchmarks.paper import main as bench_main

    return int(bench_main(list(args.bench_args)))
