"""The evaluation's two targets, measured: pick-and-place success on the onboard strategy with one robot
(at least 95%), over several seeded scenes; and real time kept by the physics of 4 robots (real-time factor
at least 1), read from the matrix's rows.

    python -m kuberos_sim.targets --seeds 1-7 --out sim/results     # after python -m kuberos_sim.evaluate

Writes `targets.md` and `targets.json` beside the matrix's results.
"""

from __future__ import annotations

import argparse
import json
import os
import sys

from kuberos_sim import evaluate, scenario

SUCCESS_TARGET = 0.95
RTF_TARGET = 1.0


seed_list = evaluate.seed_list


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m kuberos_sim.targets", description=__doc__.split("\n\n")[0])
    parser.add_argument("--seeds", default="1-7", help="scenes, e.g. 1-7 or 1,4,9 (default 1-7)")
    parser.add_argument("--cycles", type=int, default=3, help="pick cycles per scene (default 3)")
    parser.add_argument("--rate", type=float, default=4, help="tasks per minute (default 4)")
    parser.add_argument("--out", default=os.path.join(scenario.ROOT, "sim", "results"))
    args = parser.parse_args(argv)
    try:
        seeds = seed_list(args.seeds)
    except ValueError:
        parser.error(f"--seeds {args.seeds!r}: expected numbers and ranges such as 1-7 or 1,4,9")
    out = os.path.abspath(args.out)
    runs = []
    for seed in seeds:
        evaluate.progress(f"onboard, 1 robot, seed {seed}")
        directory = os.path.join(out, "targets", f"seed-{seed}")
        try:
            row = evaluate.run_one("onboard", 1, args.rate, args.cycles, directory, seed, 240, 0.125)
        except (RuntimeError, OSError) as error:
            row = {"error": str(error)[:500], "cycles": 0, "cycles_ok": 0}
        runs.append({"seed": seed, **row})
        evaluate.progress(f"  {row.get('cycles_ok')}/{row.get('cycles')} cycles succeeded")
    cycles = sum(r.get("cycles") or 0 for r in runs)
    ok = sum(r.get("cycles_ok") or 0 for r in runs)
    rtf = []
    matrix = os.path.join(out, "results.json")
    if os.path.exists(matrix):
        with open(matrix, encoding="utf-8") as handle:
            rtf = [
                (r["strategy"], r["rate_per_min"], r.get("rtf_min")) for r in json.load(handle)["rows"] if r.get("robots") == 4
            ]
    result = {
        "command": " ".join(["python -m kuberos_sim.targets", *(argv if argv is not None else sys.argv[1:])]),
        "commit": evaluate.git_commit(),
        "machine": evaluate.machine(),
        "success": {"cycles": cycles, "ok": ok, "rate": ok / cycles if cycles else None, "target": SUCCESS_TARGET},
        "success_runs": runs,
        "rtf_4_robots": [{"strategy": s, "rate_per_min": rate, "rtf_min": v} for s, rate, v in rtf],
    }
    with open(os.path.join(out, "targets.json"), "w", encoding="utf-8") as handle:
        json.dump(result, handle, indent=1)
    rate = result["success"]["rate"]
    verdict = "met" if rate is not None and rate >= SUCCESS_TARGET else "NOT met"
    lines = [
        "# Targets",
        "",
        f"- command: `{result['command']}`; commit {result['commit']}; machine: {result['machine']}",
        "",
        f"Pick-and-place success, onboard strategy, 1 robot, seeds {args.seeds} x {args.cycles} cycles: "
        f"**{ok}/{cycles}** = {rate:.1%} (target at least {SUCCESS_TARGET:.0%}: {verdict})."
        if rate is not None
        else "Pick-and-place success: no cycle ran.",
        "",
        "| seed | cycles | succeeded | plan p50 ms | pick cycle p50 s |",
        "|---|---|---|---|---|",
        *(
            f"| {r['seed']} | {r.get('cycles')} | {r.get('cycles_ok')} | "
            f"{r.get('plan_p50_ms', '-')} | {r.get('cycle_p50_s', '-')} |"
            for r in runs
        ),
        "",
        "Real-time factor of the physics with 4 robots (lowest robot, at the end of each run; target at least 1):",
        "",
        "| strategy | tasks/min | RTF min |",
        "|---|---|---|",
        *(f"| {s} | {rate_:g} | {v} |" for s, rate_, v in rtf),
        "",
    ]
    with open(os.path.join(out, "targets.md"), "w", encoding="utf-8") as handle:
        handle.write("\n".join(lines))
    evaluate.progress(f"targets in {out}/targets.md")
    return 0


if __name__ == "__main__":
    sys.exit(main())
