"""The evaluation's table (results.md) and plots (PNG) from its rows (results.json).

`results.json` keeps one row per run: strategy, fleet size, rate and seed. The table and the plots show one line
per combination: for every figure the median over the seeds that ran, and the spread (lowest to highest) when
there is more than one, `median (min-max)`. Counts (cycles, successful cycles, objects on the platform) are summed
over the seeds, the success rate is pooled (successful cycles / cycles started) with the seeds' own rates as its
spread, and "all ran" counts the seeds whose robots were all ready and ran every cycle in time. A seed whose run
failed is named under the table; a combination without any run is a `failed` line.
"""

from __future__ import annotations

import json
import os
import statistics
import sys

COLUMNS = [
    ("strategy", "strategy"),
    ("robots", "robots"),
    ("rate_per_min", "tasks/min/robot"),
    ("seeds", "seeds"),
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
    ("startup_s", "start-up s"),
]
SUMMED = ("cycles", "cycles_ok", "plans", "plans_ok", "on_platform")
KEY = ("strategy", "robots", "rate_per_min")


def cell(value) -> str:
    if value is None:
        return "-"
    if isinstance(value, float):
        return f"{value:g}"
    return str(value)


def _number(value: float, digits: int = 4) -> str:
    return f"{float(f'{value:.{digits}g}'):g}" if abs(value) < 10**digits else f"{value:.0f}"


def spread(values: list[float]) -> dict | None:
    """Median, lowest and highest of the values that are there; None for none."""
    data = sorted(v for v in values if v is not None)
    if not data:
        return None
    return {"median": statistics.median(data), "min": data[0], "max": data[-1], "n": len(data)}


def spread_text(stats: dict | None, percent: bool = False) -> str:
    if stats is None:
        return "-"
    show = (lambda v: f"{v:.0%}") if percent else _number
    if stats["n"] == 1 or stats["min"] == stats["max"]:
        return show(stats["median"])
    return f"{show(stats['median'])} ({show(stats['min'])}-{show(stats['max'])})"


def aggregate(rows: list[dict], default_seed: int | None = None) -> list[dict]:
    """One entry per (strategy, robots, rate), in the rows' order: the per-seed rows that ran (`runs`), those that
    failed (`failed`), per figure its `spread` over the runs, summed counts, the pooled success rate."""
    groups: dict[tuple, dict] = {}
    for row in rows:
        key = tuple(row[k] for k in KEY)
        group = groups.setdefault(key, {**dict(zip(KEY, key, strict=True)), "runs": [], "failed": []})
        seed = row.get("seed", default_seed)
        (group["failed"] if "error" in row else group["runs"]).append({**row, "seed": seed})
    for group in groups.values():
        runs = group["runs"]
        group["seeds"] = sorted({r["seed"] for r in runs + group["failed"]}, key=lambda s: (s is None, s))
        figures = {k for r in runs for k, v in r.items() if isinstance(v, int | float) and not isinstance(v, bool)}
        group["spread"] = {k: spread([r.get(k) for r in runs]) for k in sorted(figures - set(KEY) - {"seed"})}
        for k in SUMMED:
            group[k] = sum(r.get(k) or 0 for r in runs)
        group["success_rate"] = group["cycles_ok"] / group["cycles"] if group["cycles"] else None
        group["finished"] = sum(1 for r in runs if r.get("finished"))
    return list(groups.values())


def _group_cell(group: dict, key: str) -> str:
    runs = group["runs"]
    if key in KEY:
        return f"{group[key]:g}" if isinstance(group[key], float) else str(group[key])
    if key == "seeds":
        ran = len(runs)
        total = ran + len(group["failed"])
        return str(ran) if ran == total else f"{ran} of {total}"
    if key == "success_rate":
        if group["success_rate"] is None:
            return spread_text(group["spread"].get("success_rate"), percent=True)  # rows without counts
        pooled = f"{group['success_rate']:.0%}"
        rates = group["spread"].get("success_rate")
        if rates and rates["n"] > 1 and rates["min"] != rates["max"]:
            pooled += f" ({rates['min']:.0%}-{rates['max']:.0%})"
        return pooled
    if key in SUMMED:
        return str(group[key])
    if key == "finished":
        if len(runs) == 1:
            return str(group["finished"] == 1)
        return f"{group['finished']}/{len(runs)}"
    return spread_text(group["spread"].get(key))


def table(rows: list[dict], default_seed: int | None = None) -> str:
    lines = ["| " + " | ".join(title for _, title in COLUMNS) + " |", "|" + "---|" * len(COLUMNS)]
    for group in aggregate(rows, default_seed):
        head = f"| {group['strategy']} | {group['robots']} | {group['rate_per_min']:g} |"
        if not group["runs"]:
            reason = " ".join(group["failed"][0]["error"].split())[:160].replace("|", "/")
            lines.append(f"{head} failed: {reason} |")
            continue
        lines.append("| " + " | ".join(_group_cell(group, key) for key, _ in COLUMNS) + " |")
    return "\n".join(lines)


def problems(rows: list[dict], default_seed: int | None = None) -> list[str]:
    """One line per run that failed, or whose robots were not all ready (what the table's counts leave out)."""
    lines = []
    for row in rows:
        name = f"{row['strategy']}/{row['robots']}/{row['rate_per_min']:g}, seed {row.get('seed', default_seed)}"
        if "error" in row:
            lines.append(f"- {name}: failed: {' '.join(row['error'].split())[:300]}")
        elif row.get("not_ready"):
            missing = "; ".join(f"{robot}: {why}" for robot, why in sorted(row["not_ready"].items()))
            lines.append(f"- {name}: {row.get('robots_ready', 0)} of {row['robots']} robots ready ({missing[:300]})")
    return lines


def commits_note(rows: list[dict]) -> str:
    """The rows that ran with another commit than most (a resumed evaluation)."""
    by_commit: dict[str, list[str]] = {}
    for row in rows:
        if row.get("commit"):
            seed = f"/s{row['seed']}" if "seed" in row else ""
            by_commit.setdefault(row["commit"], []).append(f"{row['strategy']}/{row['robots']}/{row['rate_per_min']:g}{seed}")
    if len(by_commit) < 2:
        return ""
    usual = max(by_commit, key=lambda c: len(by_commit[c]))
    others = "; ".join(f"{', '.join(names)}: {c}" for c, names in by_commit.items() if c != usual)
    return f" (other commits: {others})"


def seeds_of(results: dict) -> list:
    if results.get("seeds"):
        return list(results["seeds"])
    return [results.get("seed")] if results.get("seed") is not None else []


def write(out: str, results: dict) -> None:
    rows = results["rows"]
    seeds = seeds_of(results)
    default_seed = seeds[0] if len(seeds) == 1 else None
    with open(os.path.join(out, "results.json"), "w", encoding="utf-8") as handle:
        json.dump(results, handle, indent=1)
    seed_text = f"seed {seeds[0]}" if len(seeds) == 1 else f"seeds {', '.join(str(s) for s in seeds)}"
    issues = problems(rows, default_seed)
    text = [
        "# Pick-and-place evaluation: results",
        "",
        f"- command: `{results['command']}`",
        f"- commit: {results['commit']}" + commits_note(rows),
        f"- machine: {results['machine']}",
        f"- date: {results['date']}",
        f"- pick cycles per robot: {results['cycles_per_robot']}, {seed_text}, "
        f"cgroup cores per inventory CPU: {results['cpu_scale']}",
        "",
        "What the columns mean and what the figures show: docs/simulation.md. With several seeds each figure is the "
        "median over the seeds and, in brackets, the lowest and highest; counts are summed over the seeds, success "
        "is pooled, and 'all ran' counts the seeds whose every robot was ready and ran every cycle in time.",
        "",
        table(rows, default_seed),
        "",
        *(["Runs that failed or did not start every robot:", "", *issues, ""] if issues else []),
        "![planning latency](planning_latency.png)",
        "![pick cycle time](cycle_time.png)",
        "![CPU per node class](cpu_per_class.png)",
        "",
    ]
    with open(os.path.join(out, "results.md"), "w", encoding="utf-8") as handle:
        handle.write("\n".join(text))
    plots(out, rows, default_seed)


def series(groups: list[dict], rate: float, key: str) -> dict[str, list[tuple[int, dict]]]:
    """strategy -> [(robots, spread of `key` over the seeds)], sorted by fleet size, for one rate."""
    by_strategy: dict[str, list[tuple[int, dict]]] = {}
    for group in groups:
        stats = group["spread"].get(key)
        if group["rate_per_min"] == rate and stats is not None:
            by_strategy.setdefault(group["strategy"], []).append((group["robots"], stats))
    return {s: sorted(points, key=lambda p: p[0]) for s, points in by_strategy.items()}


def plots(out: str, rows: list[dict], default_seed: int | None = None) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    groups = [g for g in aggregate(rows, default_seed) if g["runs"]]
    rates = sorted({g["rate_per_min"] for g in groups})
    if not rates:
        return
    several = any(len(g["runs"]) > 1 for g in groups)
    over = "median over seeds, bar: lowest to highest seed" if several else "one seed"
    for key, tail, title, ylabel, filename in (
        ("plan_p50_ms", "plan_p95_ms", "Planning latency p50 (dashed: p95)", "ms", "planning_latency.png"),
        ("cycle_p50_s", "cycle_p95_s", "Pick cycle time p50 (dashed: p95)", "s", "cycle_time.png"),
    ):
        figure, axes = plt.subplots(1, len(rates), figsize=(5 * len(rates), 3.8), squeeze=False, sharey=True)
        for ax, rate in zip(axes[0], rates, strict=True):
            tails = series(groups, rate, tail)
            for strategy, points in series(groups, rate, key).items():
                xs = [x for x, _ in points]
                ys = [s["median"] for _, s in points]
                errors = [
                    [y - s["min"] for y, (_, s) in zip(ys, points, strict=True)],
                    [s["max"] - y for y, (_, s) in zip(ys, points, strict=True)],
                ]
                line = ax.errorbar(xs, ys, yerr=errors, marker="o", capsize=3, label=strategy)
                if strategy in tails:
                    tx = [x for x, _ in tails[strategy]]
                    ty = [s["median"] for _, s in tails[strategy]]
                    ax.plot(tx, ty, linestyle="--", marker=".", alpha=0.5, color=line.lines[0].get_color())
            ax.set_title(f"{rate:g} tasks/min per robot")
            ax.set_xlabel("robots in the fleet")
            ax.set_xscale("log", base=2)
            ax.set_yscale("log")
            sizes = sorted({g["robots"] for g in groups})
            ax.set_xticks(sizes, [str(n) for n in sizes])
            ax.grid(alpha=0.3)
        axes[0][0].set_ylabel(ylabel)
        axes[0][-1].legend(fontsize=8)
        figure.suptitle(f"{title}; {over}", fontsize=10)
        figure.tight_layout()
        figure.savefig(os.path.join(out, filename), dpi=110)
        plt.close(figure)
    rate = max(rates)
    sizes = sorted({g["robots"] for g in groups})
    tiers = ("onboard", "edge", "cloud", "sim")
    figure, axes = plt.subplots(1, len(sizes), figsize=(3.6 * len(sizes), 3.8), squeeze=False, sharey=True)
    for ax, size in zip(axes[0], sizes, strict=True):
        chosen = [g for g in groups if g["robots"] == size and g["rate_per_min"] == rate]
        names = [g["strategy"] for g in chosen]
        bottom = [0.0] * len(chosen)
        for tier in tiers:
            values = [(g["spread"].get(f"cpu_{tier}_cores") or {"median": 0.0})["median"] for g in chosen]
            ax.bar(names, values, bottom=bottom, label="physics" if tier == "sim" else tier)
            bottom = [b + v for b, v in zip(bottom, values, strict=True)]
        if several:
            totals = [spread([sum(r.get(f"cpu_{t}_cores") or 0.0 for t in tiers) for r in g["runs"]]) for g in chosen]
            low = [max(0.0, b - t["min"]) for b, t in zip(bottom, totals, strict=True)]
            high = [max(0.0, t["max"] - b) for b, t in zip(bottom, totals, strict=True)]
            ax.errorbar(names, bottom, yerr=[low, high], fmt="none", ecolor="black", capsize=3)
        ax.set_title(f"{size} robot{'s' if size > 1 else ''}")
        ax.tick_params(axis="x", labelrotation=35, labelsize=8)
    axes[0][0].set_ylabel("cores used (average over the run)")
    axes[0][-1].legend(fontsize=8)
    suffix = "\nmedians over seeds; bar: lowest to highest seed's total" if several else ""
    figure.suptitle(f"CPU per node class, {rate:g} tasks/min per robot (the machine has 2 cores){suffix}", fontsize=10)
    figure.tight_layout()
    figure.savefig(os.path.join(out, "cpu_per_class.png"), dpi=110)
    plt.close(figure)


if __name__ == "__main__":
    directory = sys.argv[1] if len(sys.argv) > 1 else os.path.join(os.path.dirname(__file__), "..", "results")
    with open(os.path.join(directory, "results.json"), encoding="utf-8") as handle:
        write(directory, json.load(handle))
