"""The offline pick-and-place loop succeeds on a few seeds (the big measurement is the CLI run)."""

from __future__ import annotations

from kuberos_pnp import offline
from kuberos_pnp.planning import Planner

# pure computation, no hosts nor processes: the api lane (tests/conftest.py), beside the host lane


def test_offline_loop_places_every_target():
    reports, infos = [], []
    with Planner(parallel=2, seed=1) as planner:
        for seed in (1, 4):
            reps, info = offline.run_robot(seed, 2, 2, planner, budget=1.0, log=lambda *_: None)
            reports += reps
            infos.append(info)
    summary = offline.summarize(reports, infos)
    assert summary["cycles"] == 4
    assert summary["success_rate"] == 1.0, [r.reason for r in reports]
    assert summary["real_time_factor"] > 1.0
    assert all(i["on_platform"] == 2 for i in infos)
