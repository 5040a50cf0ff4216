"""Where every module of every robot runs against where it was placed: the rows and the table people read after a
deploy (``rosdeployment_info``, ``rosdeployment``). Pure: the rows of pods come from ``cluster_state.running_modules``."""

from __future__ import annotations


def compare(placement: dict, pods: list[dict]) -> list[dict]:
    by_instance: dict[str, list[dict]] = {}
    for pod in pods:
        by_instance.setdefault((pod["fleet"], pod["instance"]), []).append(pod)
    rows = []
    wanted = list(placement["placements"])
    for entry in placement.get("discovery", []):
        for server in entry["servers"]:
            wanted.append(
                {"deployment": f"(fleet {entry['fleet']})", "fleet": entry["fleet"], "robot": "-", "module": server["name"],
                 "tier": server["tier"], "node": server["node"], "instance": server["name"]}
            )  # fmt: skip
    for entry in placement.get("bridges", []):
        wanted.append(
            {"deployment": f"(fleet {entry['fleet']})", "fleet": entry["fleet"], "robot": "-", "module": entry["name"],
             "tier": entry["tier"], "node": entry["node"], "instance": entry["name"]}
        )  # fmt: skip
    for row in wanted:
        if row.get("cluster"):
            # Runs in a third-party cluster: applied and watched there, not here.
            rows.append(
                {"deployment": row["deployment"], "robot": row["robot"], "module": row["module"], "tier": row["tier"],
                 "placed_node": row["node"], "node": row["node"], "phase": "Remote", "ready": True, "pod": None}
            )  # fmt: skip
            continue
        live = by_instance.get((row["fleet"], row["instance"]), [])
        pod = next((p for p in live if p["ready"]), live[0] if live else None)
        rows.append(
            {
                "deployment": row["deployment"],
                "robot": row["robot"],
                "module": row["module"],
                "tier": row["tier"],
                "placed_node": row["node"],
                "node": pod["node"] if pod else None,
                "phase": pod["phase"] if pod else "Missing",
                "ready": bool(pod and pod["ready"] and pod["node"] == row["node"]),
                "pod": pod["pod"] if pod else None,
            }
        )
    return rows


def status_table(rows: list[dict]) -> str:
    header = ("DEPLOYMENT", "ROBOT", "MODULE", "TIER", "NODE (CLUSTER)", "PHASE", "PLACED ON")
    lines = [header] + [
        (
            r["deployment"],
            r["robot"],
            r["module"],
            r["tier"],
            r["node"] or "-",
            r["phase"] + ("" if r["ready"] or r["phase"] != "Running" else " (not ready)"),
            "same" if r["node"] == r["placed_node"] else r["placed_node"],
        )
        for r in rows
    ]
    widths = [max(len(str(line[i])) for line in lines) for i in range(len(header))]
    return "\n".join("  ".join(str(c).ljust(w) for c, w in zip(line, widths, strict=True)).rstrip() for line in lines)
