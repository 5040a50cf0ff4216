"""The evaluation's pure parts: strategy specs place modules where the strategy says (with the collection's own
scheduler), the figures computed from result records, the request conventions, and the table."""

from __future__ import annotations

import pytest
from kuberos_pnp import common
from kuberos_sim import metrics, report, scenario

from ansible_collections.kuberos.platform.plugins.module_utils.kuberos import service

pytestmark = pytest.mark.sim


def raw_inventory(robots: int) -> dict:
    """The scenario's Ansible inventory as the fleet_inventory filter would hand it to the core."""
    root = scenario.site_inventory(robots)["all"]
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


def test_table_has_a_row_per_run_and_says_why_one_failed():
    rows = [
        {"strategy": "cloud", "robots": 1, "rate_per_min": 4.0, "success_rate": 1.0, "plan_p50_ms": 120.5},
        {"strategy": "onboard", "robots": 8, "rate_per_min": 12.0, "error": "rendering failed"},
    ]
    text = report.table(rows)
    lines = text.splitlines()
    assert len(lines) == 4 and "| cloud | 1 | 4 | 120.5 |" in lines[2] and "100%" in lines[2]
    assert "failed: rendering failed" in lines[3]
