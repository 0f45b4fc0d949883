from __future__ import annotations

import numpy as np
import pytest

from rotavg_ros.core.metrics import align_gauge, angular_errors_deg, evaluate
from rotavg_ros.core.so3 import random_rotations, rotation_about_axis


def test_recovers_right_gauge_noise_free() -> None:
    rng = np.random.default_rng(0)
    G = random_rotations(40, rng)
    Q = random_rotations(1, rng)[0]
    Qa = align_gauge(G @ Q, G)
    np.testing.assert_allclose(Qa, Q, rtol=0, atol=1e-9)
    assert angular_errors_deg(G @ Q, G, Qa).max() < 1e-9
    # A left gauge is not a symmetry of world-to-node rotations: errors stay large.
    assert angular_errors_deg(Q @ G, G, align_gauge(Q @ G, G)).max() > 1.0


def test_l1_alignment_ignores_outliers() -> None:
    rng = np.random.default_rng(1)
    n = 100
    G = random_rotations(n, rng)
    Q = random_rotations(1, rng)[0]
    E = G @ Q
    bad = rng.choice(n, 30, replace=False)
    axes = rng.normal(size=(30, 3))
    E[bad] = rotation_about_axis(axes, rng.uniform(1.0, 3.0, 30)) @ E[bad]
    clean = np.setdiff1d(np.arange(n), bad)
    Q_l2 = align_gauge(E, G, max_iters=0)
    assert np.median(angular_errors_deg(E[clean], G[clean], Q_l2)) > 1e-3
    Q_l1 = align_gauge(E, G)
    assert np.median(angular_errors_deg(E[clean], G[clean], Q_l1)) < 1e-6
    np.testing.assert_allclose(Q_l1, Q, atol=1e-9)


def test_evaluate_common_ids_and_stats() -> None:
    rng = np.random.default_rng(2)
    G = random_rotations(5, rng)
    Q = random_rotations(1, rng)[0]
    est = {f"n{k}": G[k] @ Q for k in range(5)}
    est["n4"] = rotation_about_axis([0.0, 0.0, 1.0], np.radians(10.0)) @ est["n4"]
    est["extra"] = np.eye(3)
    gt = {f"n{k}": G[k] for k in range(5)}
    s = evaluate(est, gt)
    assert s.num_nodes == 5 and s.ids == [f"n{k}" for k in range(5)]
    assert s.median_deg < 1e-9
    assert s.max_deg == pytest.approx(10.0, abs=1e-9)
    assert s.mean_deg == pytest.approx(2.0, abs=1e-9)
    with pytest.raises(ValueError, match="no common"):
        evaluate({"a": np.eye(3)}, {"b": np.eye(3)})
