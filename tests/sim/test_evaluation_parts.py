"""The evaluation's pure parts: strategy specs place modules where the strategy says (with the collection's own
scheduler), the figures computed from result records, the request conventions, and the table."""

from __future__ import annotations

import json

import pytest
from kuberos_pnp import common
from kuberos_sim import metrics, report, scenario

from ansible_collections.kuberos.platform.plugins.module_utils.kuberos import service

# pure computation, no hosts nor processes: the api lane (tests/conftest.py), beside the host lane


def raw_inventory(robots: int, strategy: str = "") -> dict:
    """The scenario's Ansible inventory as the fleet_inventory filter would hand it to the core."""
    root = scenario.site_inventory(robots, strategy)["all"]
    hosts, groups = {}, {}
    for group, body in root["children"].items():
        groups[group] = sorted(body["hosts"])
        for host, host_vars in body["hosts"].items():
            hosts[host] = {**body.get("vars", {}), **host_vars}
    return {"hosts": hosts, "groups": groups, "default_latency_ms": root["vars"]["kuberos_default_latency_ms"]}


@pytest.mark.parametrize(
    ("strategy", "tier", "instances"),
    [("onboard", "onboard", 4), ("edge-dedicated", "edge", 4), ("edge-shared", "edge", 1), ("cloud", "cloud", 4)],
)
def test_strategy_places_perception_and_planner(strategy, tier, instances):
    spec = scenario.strategy_spec(strategy, 6, 3)
    _deployments, placement = service.load_and_place(spec, raw_inventory(4))
    for module in scenario.OFFLOADED:
        placed = [i for i in placement.instances if i.module == module]
        assert {i.tier for i in placed} == {tier}, (module, [(i.name, i.node) for i in placed])
        assert len(placed) == instances
    controllers = [i for i in placement.instances if i.module == "controller"]
    assert all(i.tier == "onboard" for i in controllers)
    (coordinator,) = [i for i in placement.instances if i.module == "task-coordinator"]
    launch = next(m for m in spec["rosModules"] if m["name"] == "task-coordinator")["launch"][0]
    assert coordinator.tier == "edge" and "tasks_per_minute:=6" in launch and "max_cycles:=3" in launch


def test_unknown_strategy_is_refused():
    with pytest.raises(ValueError, match="unknown strategy 'moon'"):
        scenario.strategy_spec("moon", 6, 3)


def test_percentile():
    assert metrics.percentile([], 50) is None
    assert metrics.percentile([3.0], 95) == 3.0
    assert metrics.percentile([1, 2, 3, 4], 50) == 2.5
    assert metrics.percentile([None, 1, 3], 50) == 2


def test_summarize_counts_what_happened():
    records = [
        {"kind": "plan", "latency_ms": 100.0, "planning_ms": 60.0, "ok": True, "node": "edge-1", "planner_node": "cloud-1"},
        {"kind": "plan", "latency_ms": 300.0, "planning_ms": 250.0, "ok": True, "node": "edge-1", "planner_node": "edge-1"},
        {"kind": "plan", "latency_ms": 30000.0, "ok": False, "reason": "timeout", "node": "edge-1"},
        {"kind": "cycle", "outcome": "success", "duration_s": 10.0},
        {"kind": "cycle", "outcome": "failed", "duration_s": 40.0},
        {"kind": "sim", "robot": "robot-1", "rtf": 0.98, "on_platform": 0},
        {"kind": "sim", "robot": "robot-1", "rtf": 1.0, "on_platform": 1},
    ]
    row = metrics.summarize(records, {"onboard": 5.0, "edge": 20.0, "sim": 10.0}, window_s=10.0, robots=1)
    assert (row["plans"], row["plans_ok"], row["cycles"], row["cycles_ok"]) == (3, 2, 2, 1)
    assert row["plan_p50_ms"] == 200.0 and row["planning_compute_p50_ms"] == 155.0  # the timeout is left out
    assert row["success_rate"] == 0.5 and row["cycle_p50_s"] == 10.0  # failed cycles have no cycle time
    assert row["rtf_min"] == 1.0 and row["on_platform"] == 1  # each robot's last report
    assert (row["cpu_onboard_cores"], row["cpu_edge_cores"], row["cpu_cloud_cores"], row["cpu_sim_cores"]) == (0.5, 2.0, 0.0, 1.0)
    assert row["crossed_hosts"] == 1


def test_request_conventions_round_trip():
    tag = common.encode_tag("robot-1/7", scene="12.000000005", ignore=common.encode_names(["target_0", "table"]))
    request_id, values = common.decode_tag(tag)
    assert request_id == "robot-1/7" and values["scene"] == "12.000000005"
    assert common.decode_names(values["ignore"]) == ("target_0", "table")
    assert common.decode_carry(None) is None
    assert common.robot_namespace("robot-1") == "/robot_1" and common.robot_namespace("9x") == "/r_9x"
    records = common.read_results('noise\nKUBEROS_RESULT {"kind": "plan", "ok": true}\nKUBEROS_RESULT {"kind": "cy')
    assert records == [{"kind": "plan", "ok": True}]  # a line cut off by a killed process is skipped


def test_carried_object_crosses_exactly():
    """The planner checks the carried cube where the coordinator's IK did: its pose in the grasp frame is not
    rounded on the way (it was, to 6 decimals)."""
    from kuberos_pnp import perception_core, planning

    box = perception_core.Box("target_0", "target", (0.7, -0.1, 0.425), (0.05, 0.05, 0.05))
    carry = planning.Attached(
        box, (1e-7, -2.000000049e-3, 0.0123456789012), (1.0, 3.3e-9, 0.0, 6.123233995736766e-17), ("table",)
    )
    name, position, quat, ignore = common.decode_carry(common.encode_carry(carry))
    assert (name, position, quat, ignore) == ("target_0", carry.ee_position, carry.ee_quat_xyzw, ("table",))
    tag = common.encode_tag("robot-1/3", carry=common.encode_carry(carry))
    assert common.decode_carry(common.decode_tag(tag)[1]["carry"])[1] == carry.ee_position


def test_table_has_a_row_per_run_and_says_why_one_failed():
    rows = [
        {"strategy": "cloud", "robots": 1, "rate_per_min": 4.0, "success_rate": 1.0, "plan_p50_ms": 120.5},
        {"strategy": "onboard", "robots": 8, "rate_per_min": 12.0, "error": "rendering failed"},
    ]
    text = report.table(rows)
    lines = text.splitlines()
    assert len(lines) == 4 and "| cloud | 1 | 4 | 1 | 120.5 |" in lines[2] and "100%" in lines[2]
    assert "failed: rendering failed" in lines[3]


def seeded_rows() -> list[dict]:
    """Synthetic per-seed rows of the evaluation (no simulation): cloud and onboard, 1 and 2 robots, 2 rates,
    seeds 1-3; seed 2 of cloud/2/12 failed, seed 3 of onboard/2/4 started 1 of its 2 robots."""
    rows = []
    for strategy, base in (("cloud", 200.0), ("onboard", 400.0)):
        for robots in (1, 2):
            for rate in (4.0, 12.0):
                for seed in (1, 2, 3):
                    if (strategy, robots, rate, seed) == ("cloud", 2, 12.0, 2):
                        rows.append({"strategy": strategy, "robots": robots, "rate_per_min": rate, "seed": seed, "error": "boom"})
                        continue
                    late = (strategy, robots, rate, seed) == ("onboard", 2, 4.0, 3)
                    cycles = 3 * robots
                    ok = cycles - (seed == 3)
                    rows.append(
                        {
                            "strategy": strategy,
                            "robots": robots,
                            "rate_per_min": rate,
                            "seed": seed,
                            "plan_p50_ms": base * robots + 10.0 * seed,
                            "plan_p95_ms": 3 * base * robots + 10.0 * seed,
                            "cycle_p50_s": 10.0 + seed,
                            "cycle_p95_s": 14.0 + seed,
                            "cycles": cycles,
                            "cycles_ok": ok,
                            "success_rate": ok / cycles,
                            "on_platform": ok,
                            "finished": not late,
                            "robots_ready": robots - late,
                            **({"not_ready": {"robot-2": "not ready within 600 s: no planner"}} if late else {}),
                            "cpu_onboard_cores": 0.1 * seed,
                            "cpu_edge_cores": 0.05,
                            "cpu_cloud_cores": 0.2 if strategy == "cloud" else 0.0,
                            "cpu_sim_cores": 0.2,
                            "rtf_min": 1.0,
                            "startup_s": 20.0 + seed,
                        }
                    )
    return rows


def test_seed_lists():
    from kuberos_sim import evaluate

    assert evaluate.seed_list("1-3") == [1, 2, 3]
    assert evaluate.seed_list("1,4,9") == [1, 4, 9]
    assert evaluate.seed_list("1-3,7,2") == [1, 2, 3, 7]
    for bad in ("", "a", "1-b"):
        with pytest.raises(ValueError):
            evaluate.seed_list(bad)
    assert evaluate.run_name("edge-shared", 4, 12.0, 2) == "edge-shared-r4-t12-s2"


def test_table_shows_the_median_and_spread_over_seeds():
    lines = report.table(seeded_rows()).splitlines()
    assert len(lines) == 2 + 8  # one line per strategy, fleet size and rate, not per seed
    header = [c.strip() for c in lines[0].split("|")][1:-1]
    row = dict(zip(header, [c.strip() for c in lines[2].split("|")][1:-1], strict=True))
    assert (row["strategy"], row["robots"], row["tasks/min/robot"], row["seeds"]) == ("cloud", "1", "4", "3")
    assert row["plan p50 ms"] == "220 (210-230)"  # median (lowest-highest) of 210, 220, 230
    assert row["cycles"] == "9" and row["on platform (physics)"] == "8"  # summed over the seeds
    assert row["success"] == "89% (67%-100%)"  # 8 of 9 pooled; the seeds' own rates as the spread
    assert row["all ran"] == "3/3" and row["CPU edge"] == "0.05" and row["start-up s"] == "22 (21-23)"
    by_name = {tuple(c.strip() for c in line.split("|")[1:4]): line for line in lines[2:]}
    failed_seed = dict(zip(header, [c.strip() for c in by_name[("cloud", "2", "12")].split("|")][1:-1], strict=True))
    assert failed_seed["seeds"] == "2 of 3" and failed_seed["cycles"] == "12"
    late = dict(zip(header, [c.strip() for c in by_name[("onboard", "2", "4")].split("|")][1:-1], strict=True))
    assert late["all ran"] == "2/3"
    problems = report.problems(seeded_rows())
    assert problems == [
        "- cloud/2/12, seed 2: failed: boom",
        "- onboard/2/4, seed 3: 1 of 2 robots ready (robot-2: not ready within 600 s: no planner)",
    ]


def test_one_seed_reads_as_before_and_old_results_have_their_seed():
    rows = [r for r in seeded_rows() if r["seed"] == 1]
    for row in rows:
        row.pop("seed")
    line = report.table(rows, default_seed=1).splitlines()[2]
    assert "| cloud | 1 | 4 | 1 | 210 | 610 |" in line and "| 100% | 3 | 3 | True |" in line
    assert report.seeds_of({"seed": 1}) == [1] and report.seeds_of({"seeds": [1, 2, 3], "seed": 9}) == [1, 2, 3]
    groups = report.aggregate(rows, default_seed=1)
    assert groups[0]["runs"][0]["seed"] == 1


def test_report_keeps_per_seed_rows_and_draws_the_spread(tmp_path):
    results = {
        "command": "python -m kuberos_sim.evaluate --seeds 1-3",
        "commit": "abc1234",
        "machine": "2 cores",
        "date": "2026-11-26 00:00 UTC",
        "cycles_per_robot": 3,
        "seeds": [1, 2, 3],
        "cpu_scale": 0.125,
        "rows": seeded_rows(),
    }
    report.write(str(tmp_path), results)
    with open(tmp_path / "results.json", encoding="utf-8") as handle:
        kept = json.load(handle)
    assert len(kept["rows"]) == 24 and {r["seed"] for r in kept["rows"]} == {1, 2, 3}
    text = (tmp_path / "results.md").read_text(encoding="utf-8")
    assert "seeds 1, 2, 3" in text and "220 (210-230)" in text and "- cloud/2/12, seed 2: failed: boom" in text
    for name in ("planning_latency.png", "cycle_time.png", "cpu_per_class.png"):
        assert (tmp_path / name).stat().st_size > 10_000
    points = report.series(report.aggregate(kept["rows"]), 4.0, "plan_p50_ms")
    assert points["cloud"][0][0] == 1 and points["cloud"][0][1] == {"median": 220.0, "min": 210.0, "max": 230.0, "n": 3}


def test_evaluate_runs_every_seed_and_resumes_by_seed(tmp_path, monkeypatch):
    """--seeds 1-3 runs each combination once per seed (run_one replaced: no simulation), results.json keeps the
    rows per seed; --resume keeps the rows that ran and reruns only the failed seed."""
    from kuberos_sim import evaluate

    calls = []
    broken = {2}

    def fake_run_one(strategy, robots, rate, cycles, out, seed, time_limit, cpu_scale, startup_limit):
        calls.append((strategy, robots, rate, seed, startup_limit))
        if seed in broken:
            raise RuntimeError("a process exited")
        row = next(r for r in seeded_rows() if (r["strategy"], r["robots"], r["rate_per_min"]) == (strategy, robots, rate))
        return {**row, "seed": seed, "commit": "abc1234"}

    monkeypatch.setattr(evaluate, "run_one", fake_run_one)
    args = ["--strategies", "cloud", "--robots", "1,2", "--rates", "4", "--seeds", "1-3", "--out", str(tmp_path)]
    assert evaluate.main([*args, "--startup-limit", "120"]) == 0
    assert [c[3] for c in calls] == [1, 2, 3, 1, 2, 3] and {c[4] for c in calls} == {120.0}
    with open(tmp_path / "results.json", encoding="utf-8") as handle:
        first = json.load(handle)
    assert first["seeds"] == [1, 2, 3] and [r["seed"] for r in first["rows"]] == [1, 2, 3, 1, 2, 3]
    assert [("error" in r) for r in first["rows"]] == [False, True, False, False, True, False]
    calls.clear()
    broken.clear()
    assert evaluate.main([*args, "--resume"]) == 0
    assert [(c[1], c[3]) for c in calls] == [(1, 2), (2, 2)]  # only the failed seeds ran again
    with open(tmp_path / "results.json", encoding="utf-8") as handle:
        second = json.load(handle)
    assert [r["seed"] for r in second["rows"]] == [1, 2, 3, 1, 2, 3] and not any("error" in r for r in second["rows"])
    with pytest.raises(SystemExit):
        evaluate.main([*args, "--seed", "4"])


def test_a_robot_never_ready_is_not_a_run_that_ran():
    """cloud/8/4 once showed 0 cycles with 'all ran: True': its coordinators gave up waiting for their planners and
    the evaluation took that for robots done. Robots given up at start are told apart."""
    from kuberos_sim import evaluate

    records = [
        {"kind": "ready", "robot": "robot-1", "planner_s": 12.0},
        {"kind": "idle", "robot": "robot-2", "cycle": 0, "startup": True, "reason": "not ready within 600 s: no planner"},
        {"kind": "idle", "robot": "robot-3", "cycle": 4, "reason": "no target left on the table"},
    ]
    ready, gave_up = evaluate.readiness(records, 3)
    assert ready == ["robot-1"] and gave_up == {"robot-2": "not ready within 600 s: no planner"}


def test_the_seed_reaches_the_planner_and_the_coordinator():
    spec = scenario.strategy_spec("edge-dedicated", 4, 3, seed=2, startup_timeout=600)
    modules = {m["name"]: m for m in spec["rosModules"]}
    assert modules["motion-planner"]["rosParameters"]["seed"] == 2
    launch = modules["task-coordinator"]["launch"][0]
    assert "-p seed:=2" in launch and "-p startup_timeout:=600" in launch and "max_cycles:=3" in launch


def test_the_scaled_strategy_scales_only_the_planner_on_its_queue():
    spec = scenario.strategy_spec("edge-scaled", 12, 3)
    modules = {m["name"]: m for m in spec["rosModules"]}
    assert modules["motion-planner"]["scaling"]["metric"] == "kuberos_planner_queue_depth"
    assert modules["motion-planner"]["strategy"] == "shared" and modules["perception"]["strategy"] == "shared"
    assert "scaling" not in modules["perception"]
    assert "edge-scaled" not in scenario.MATRIX and "scaling" not in str(scenario.strategy_spec("edge-shared", 12, 3))


def test_the_burst_site_holds_two_planners_on_its_edge_and_lets_the_planner_into_the_cloud():
    from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.inventory import load_inventory
    from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.scheduler import Scheduler

    spec = scenario.strategy_spec("edge-burst", 12, 4)
    raw = raw_inventory(8, "edge-burst")
    assert raw["groups"]["edge"] == ["edge-1"] and "cloud" not in raw["groups"], "no cloud node until one is launched"
    deployments, placement = service.load_and_place(spec, raw)
    (planner,) = [m for m in deployments[0].modules if m.name == "motion-planner"]
    assert planner.scaling is not None and planner.tiers == ("edge", "cloud") and planner.requirements.max_latency_ms == 50
    assert {i.node for i in placement.instances if i.tier != "onboard"} == {"edge-1"}
    scheduler = Scheduler.around(load_inventory(raw), placement)
    node, _tier, _latency, _why = scheduler.choose(deployments[0], planner, ("robot-1",))
    assert node is not None and node.name == "edge-1", "room for a second planner"
    scheduler.take(node.name, planner.resources.cpu_millis, planner.resources.memory_bytes, planner.resources.gpu)
    assert scheduler.choose(deployments[0], planner, ("robot-1",))[0] is None, "no room for a third: the cloud is lacking"
    assert "edge-burst" not in scenario.MATRIX


def test_the_planners_queue_gauge_is_a_windowed_mean_the_scaler_can_read():
    from kuberos_pnp.planner import GAUGE, Load

    from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.scaling import gauge_value

    load = Load(window=10.0)
    for tenth in range(200):  # 20 s: busy with 2 requests for the first 9 s, then idle
        load.sample(tenth / 10, 2 if tenth < 90 else 0)
    assert load.mean() == 0.0
    load.sample(20.1, 3)
    assert 0 < load.mean() < 0.1
    assert gauge_value(load.exposition(robots=4), GAUGE) == round(load.mean(), 4)
    assert gauge_value(load.exposition(robots=4), "kuberos_planner_robots") == 4
