"""The evaluation's table (results.md) and plots (PNG) from its rows (results.json)."""

from __future__ import annotations

import json
import os
import sys

COLUMNS = [
    ("strategy", "strategy"),
    ("robots", "robots"),
    ("rate_per_min", "tasks/min/robot"),
    ("plan_p50_ms", "plan p50 ms"),
    ("plan_p95_ms", "plan p95 ms"),
    ("planning_compute_p50_ms", "planner compute p50 ms"),
    ("cycle_p50_s", "pick cycle p50 s"),
    ("cycle_p95_s", "pick cycle p95 s"),
    ("success_rate", "success"),
    ("cycles", "cycles"),
    ("on_platform", "on platform (physics)"),
    ("finished", "all ran"),
    ("cpu_onboard_cores", "CPU robots (cores)"),
    ("cpu_edge_cores", "CPU edge"),
    ("cpu_cloud_cores", "CPU cloud"),
    ("cpu_sim_cores", "CPU physics"),
    ("rtf_min", "RTF min"),
]


def cell(value) -> str:
    if value is None:
        return "-"
    if isinstance(value, float):
        return f"{value:g}"
    return str(value)


def table(rows: list[dict]) -> str:
    lines = ["| " + " | ".join(title for _, title in COLUMNS) + " |", "|" + "---|" * len(COLUMNS)]
    for row in rows:
        if "error" in row:
            reason = " ".join(row["error"].split())[:160].replace("|", "/")
            lines.append(f"| {row['strategy']} | {row['robots']} | {row['rate_per_min']:g} | failed: {reason} |")
            continue
        values = []
        for key, _ in COLUMNS:
            value = row.get(key)
            values.append(f"{value:.0%}" if key == "success_rate" and value is not None else cell(value))
        lines.append("| " + " | ".join(values) + " |")
    return "\n".join(lines)


def commits_note(rows: list[dict]) -> str:
    """The rows that ran with another commit than most (a resumed evaluation)."""
    by_commit: dict[str, list[str]] = {}
    for row in rows:
        if row.get("commit"):
            by_commit.setdefault(row["commit"], []).append(f"{row['strategy']}/{row['robots']}/{row['rate_per_min']:g}")
    if len(by_commit) < 2:
        return ""
    usual = max(by_commit, key=lambda c: len(by_commit[c]))
    others = "; ".join(f"{', '.join(names)}: {c}" for c, names in by_commit.items() if c != usual)
    return f" (other commits: {others})"


def write(out: str, results: dict) -> None:
    rows = results["rows"]
    with open(os.path.join(out, "results.json"), "w", encoding="utf-8") as handle:
        json.dump(results, handle, indent=1)
    text = [
        "# Pick-and-place evaluation: results",
        "",
        f"- command: `{results['command']}`",
        f"- commit: {results['commit']}" + commits_note(rows),
        f"- machine: {results['machine']}",
        f"- date: {results['date']}",
        f"- pick cycles per robot: {results['cycles_per_robot']}, seed {results['seed']}, "
        f"cgroup cores per inventory CPU: {results['cpu_scale']}",
        "",
        "What the columns mean and what the figures show: docs/simulation.md.",
        "",
        table(rows),
        "",
        "![planning latency](planning_latency.png)",
        "![pick cycle time](cycle_time.png)",
        "![CPU per node class](cpu_per_class.png)",
        "",
    ]
    with open(os.path.join(out, "results.md"), "w", encoding="utf-8") as handle:
        handle.write("\n".join(text))
    plots(out, [r for r in rows if "error" not in r])


def _series(rows, rate, key):
    by_strategy: dict[str, list[tuple[int, float]]] = {}
    for row in rows:
        if row["rate_per_min"] == rate and row.get(key) is not None:
            by_strategy.setdefault(row["strategy"], []).append((row["robots"], row[key]))
    return {s: sorted(points) for s, points in by_strategy.items()}


def plots(out: str, rows: list[dict]) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rates = sorted({r["rate_per_min"] for r in rows})
    if not rates:
        return
    for key, low, title, ylabel, filename in (
        ("plan_p50_ms", "plan_p95_ms", "Planning latency (p50, bar to p95)", "ms", "planning_latency.png"),
        ("cycle_p50_s", "cycle_p95_s", "Pick cycle time (p50, bar to p95)", "s", "cycle_time.png"),
    ):
        figure, axes = plt.subplots(1, len(rates), figsize=(5 * len(rates), 3.8), squeeze=False, sharey=True)
        for ax, rate in zip(axes[0], rates, strict=True):
            medians, tails = _series(rows, rate, key), _series(rows, rate, low)
            for strategy, points in medians.items():
                xs, ys = [p[0] for p in points], [p[1] for p in points]
                high = dict(tails.get(strategy, []))
                errors = [[0] * len(xs), [max(0.0, high.get(x, y) - y) for x, y in zip(xs, ys, strict=True)]]
                ax.errorbar(xs, ys, yerr=errors, marker="o", capsize=3, label=strategy)
            ax.set_title(f"{rate:g} tasks/min per robot")
            ax.set_xlabel("robots in the fleet")
            ax.set_xscale("log", base=2)
            ax.set_yscale("log")
            sizes = sorted({r["robots"] for r in rows})
            ax.set_xticks(sizes, [str(n) for n in sizes])
            ax.grid(alpha=0.3)
        axes[0][0].set_ylabel(ylabel)
        axes[0][-1].legend(fontsize=8)
        figure.suptitle(title)
        figure.tight_layout()
        figure.savefig(os.path.join(out, filename), dpi=110)
        plt.close(figure)
    rate = max(rates)
    sizes = sorted({r["robots"] for r in rows})
    figure, axes = plt.subplots(1, len(sizes), figsize=(3.6 * len(sizes), 3.8), squeeze=False, sharey=True)
    for ax, size in zip(axes[0], sizes, strict=True):
        chosen = [r for r in rows if r["robots"] == size and r["rate_per_min"] == rate]
        bottom = [0.0] * len(chosen)
        for tier in ("onboard", "edge", "cloud", "sim"):
            values = [r.get(f"cpu_{tier}_cores") or 0.0 for r in chosen]
            ax.bar([r["strategy"] for r in chosen], values, bottom=bottom, label="physics" if tier == "sim" else tier)
            bottom = [b + v for b, v in zip(bottom, values, strict=True)]
        ax.set_title(f"{size} robot{'s' if size > 1 else ''}")
        ax.tick_params(axis="x", labelrotation=35, labelsize=8)
    axes[0][0].set_ylabel("cores used (average over the run)")
    axes[0][-1].legend(fontsize=8)
    figure.suptitle(f"CPU per node class, {rate:g} tasks/min per robot (the machine has 2 cores)")
    figure.tight_layout()
    figure.savefig(os.path.join(out, "cpu_per_class.png"), dpi=110)
    plt.close(figure)


if __name__ == "__main__":
    directory = sys.argv[1] if len(sys.argv) > 1 else os.path.join(os.path.dirname(__file__), "..", "results")
    with open(os.path.join(directory, "results.json"), encoding="utf-8") as handle:
        write(directory, json.load(handle))
