"""The diagnostics' judgement of a solution (``app.diagnostics``; no ROS needed)."""

from __future__ import annotations

from rotavg_ros.msg_adapters.outputs import Level

from benchmarks import regime_cases as rc
from rotavg_ros.app.accumulator import AccumulatorStats
from rotavg_ros.app.diagnostics import diagnostic_values, loop_closures_left_out
from rotavg_ros.app.parameters import settings_from_parameters
from rotavg_ros.app.session import SolveBookkeeping
from rotavg_ros.core.options import SolverOptions
from rotavg_ros.core.solver import RotationAverager


def _diagnostics(case: rc.RegimeCase, **parameters: object,
                 ) -> tuple[Level, str, dict[str, object]]:
    res = RotationAverager(SolverOptions()).solve(case.view_graph())
    stats = AccumulatorStats(received=case.num_edges, accepted=case.num_edges, rejected={},
                             notes={}, num_nodes=case.num_nodes,
                             num_measurements=case.num_edges, version=1, generation=0)
    return diagnostic_values(stats, SolveBookkeeping(last_result=res),
                             settings_from_parameters(parameters))


def test_most_loop_closures_left_out_warns() -> None:
    # 12 true closures and 24 random false ones on a 300-keyframe chain: the solution
    # rightly leaves out the 24, two thirds of the closures, and rests on the 12 that agree.
    case = rc.chain_case("test/chain/300/rand67", 300, closures=12, false_random=2 / 3)
    level, message, values = _diagnostics(case)
    assert values["loop_closures_left_out"] == "24 / 36"
    assert level == Level.WARN and "24 of 36 loop closures left out" in message
    level, message, _ = _diagnostics(case, left_out_warn_share=0.7)
    assert level == Level.OK, message


def test_a_third_of_loop_closures_left_out_is_ok() -> None:
    case = rc.chain_case("test/chain/300/rand33", 300, closures=20, false_random=1 / 3)
    level, message, values = _diagnostics(case)
    assert values["loop_closures_left_out"] == "10 / 30"
    assert level == Level.OK, message


def test_loop_closures_are_the_edges_not_trusted_as_odometry() -> None:
    case = rc.chain_case("test/chain/300/clean", 300, closures=20)
    res = RotationAverager(SolverOptions()).solve(case.view_graph())
    assert res.num_trusted_odometry in (0, 299)
    closures, left_out = loop_closures_left_out(res)
    assert closures == case.num_edges - res.num_trusted_odometry and left_out == 0
