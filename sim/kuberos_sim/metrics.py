"""The evaluation's figures from the modules' result records (kuberos_pnp.common.log_result) and the runtime's
CPU accounting. Pure: records in, one row out."""

from __future__ import annotations

import math

TIERS = ("onboard", "edge", "cloud")


def percentile(values: list[float], q: float) -> float | None:
    """Linear-interpolated percentile (q in 0..100); None for no values."""
    data = sorted(v for v in values if v is not None)
    if not data:
        return None
    position = (len(data) - 1) * q / 100
    low, high = math.floor(position), math.ceil(position)
    return data[low] + (data[high] - data[low]) * (position - low)


def summarize(records: list[dict], cpu_by_tier: dict[str, float], window_s: float, robots: int) -> dict:
    """One result row.

    - planning latency: as the coordinator saw it (request sent to path received: network, queueing and
      planning), p50/p95 over every answered request; `planning_ms`: the planner's own compute time.
    - pick cycle: task start to verified release, p50 over successful cycles.
    - success rate: successful cycles / cycles started (a cycle that failed for any reason counts).
    - CPU per node class: average cores used over the window by the module processes on robots, edge
      servers and cloud VMs (the simulator's physics is counted apart as `sim`).
    - rtf: the lowest real-time factor any robot's physics reported at its last report.
    """
    plans = [r for r in records if r.get("kind") == "plan"]
    answered = [r for r in plans if r.get("latency_ms") is not None and r.get("reason") != "timeout"]
    cycles = [r for r in records if r.get("kind") == "cycle"]
    ok = [c for c in cycles if c.get("outcome") == "success"]
    sims = {}
    for r in records:
        if r.get("kind") == "sim":
            sims[r["robot"]] = r  # the last report of each robot
    row = {
        "robots": robots,
        "plans": len(plans),
        "plans_ok": sum(1 for r in plans if r.get("ok")),
        "plan_p50_ms": _round(percentile([r["latency_ms"] for r in answered], 50)),
        "plan_p95_ms": _round(percentile([r["latency_ms"] for r in answered], 95)),
        "planning_compute_p50_ms": _round(percentile([r.get("planning_ms") for r in answered], 50)),
        "cycles": len(cycles),
        "cycles_ok": len(ok),
        "success_rate": round(len(ok) / len(cycles), 4) if cycles else None,
        "cycle_p50_s": _round(percentile([c["duration_s"] for c in ok], 50), 2),
        "cycle_p95_s": _round(percentile([c["duration_s"] for c in ok], 95), 2),
        "rtf_min": min((s["rtf"] for s in sims.values() if s.get("rtf") is not None), default=None),
        "on_platform": sum(s.get("on_platform", 0) for s in sims.values()),
        "window_s": round(window_s, 1),
    }
    for tier in (*TIERS, "sim"):
        row[f"cpu_{tier}_cores"] = round(cpu_by_tier.get(tier, 0.0) / window_s, 3) if window_s > 0 else None
    row["crossed_hosts"] = sum(1 for r in answered if r.get("planner_node") and r.get("planner_node") != r.get("node"))
    return row


def _round(value, digits: int = 1):
    return None if value is None else round(value, digits)
