#!/usr/bin/env python3
"""Draw the controller failover benchmark as an SVG timeline: one bar per trial, split into the grace period,
the controller's decision (grace end to its first "moved" log line) and the new pods starting (to all Running).

    .venv/bin/python bench/plot_failover.py bench/results/controller-failover.json docs/images/controller-failover.svg
"""

from __future__ import annotations

import json
import sys
from html import escape

TARGET_S = 15.0
TITLE = "Node NotReady to every affected module Running elsewhere"
ROW, LEFT, RIGHT, TOP = 22, 150, 30, 78
PARTS = (("grace", "#b0b7c3"), ("decide and write", "#f0a03c"), ("new pods start", "#3c7df0"))


def segments(trial: dict) -> list[float]:
    grace = trial.get("grace_end_offset_s") or 0.0
    first = trial.get("first_move_s") or grace
    return [grace, max(first - grace, 0.0), max(trial["seconds"] - first, 0.0)]


def draw(data: dict) -> str:
    trials = [t for t in data["trials"] if t.get("seconds") is not None]
    summary = data["summary"]
    width = 760
    scale = (width - LEFT - RIGHT) / max(TARGET_S + 1, max(t["seconds"] for t in trials) + 1)
    height = TOP + ROW * len(trials) + 70
    out = [
        f'<svg xmlns="http://www.w3.org/2000/svg" width="{width}" height="{height}" font-family="sans-serif" font-size="12">',
        f'<rect width="{width}" height="{height}" fill="white"/>',
        f'<text x="{LEFT}" y="20" font-size="14" font-weight="bold">{TITLE}</text>',
        f'<text x="{LEFT}" y="38">{escape(data.get("date", ""))}: {len(trials)} trials, grace {data["args"]["grace"]:g} s; '
        f"p50 {summary['p50']:.2f} s, p95 {summary['p95']:.2f} s (target p95 &lt; {TARGET_S:g} s)</text>",
    ]
    bottom = TOP + ROW * len(trials)
    for second in range(0, int(TARGET_S) + 2, 1):
        x = LEFT + second * scale
        out.append(f'<line x1="{x:.1f}" y1="{TOP}" x2="{x:.1f}" y2="{bottom}" stroke="#eee"/>')
        if second % 5 == 0:
            out.append(f'<text x="{x:.1f}" y="{bottom + 16}" text-anchor="middle">{second} s</text>')
    for index, trial in enumerate(trials):
        y = TOP + index * ROW
        label = f"{index + 1}: {escape(trial['node'])} ({len(trial['affected'])})"
        out.append(f'<text x="{LEFT - 8}" y="{y + 14}" text-anchor="end">{label}</text>')
        x = LEFT
        for (name, colour), seconds in zip(PARTS, segments(trial), strict=True):
            w = seconds * scale
            tip = f"<title>{name} {seconds:.2f} s</title>"
            out.append(f'<rect x="{x:.1f}" y="{y + 3}" width="{w:.1f}" height="{ROW - 6}" fill="{colour}">{tip}</rect>')
            x += w
        out.append(f'<text x="{x + 4:.1f}" y="{y + 14}">{trial["seconds"]:.2f} s</text>')
    marks = (("p50", summary["p50"], "#333", 8), ("p95", summary["p95"], "#333", 20), ("target", TARGET_S, "#c00", 8))
    for label, value, colour, above in marks:
        x = LEFT + value * scale
        out.append(f'<line x1="{x:.1f}" y1="{TOP - 4}" x2="{x:.1f}" y2="{bottom}" stroke="{colour}" stroke-dasharray="4 3"/>')
        out.append(f'<text x="{x:.1f}" y="{TOP - above}" text-anchor="middle" fill="{colour}">{label}</text>')
    x = LEFT
    for name, colour in PARTS:
        out.append(f'<rect x="{x}" y="{bottom + 30}" width="12" height="12" fill="{colour}"/>')
        out.append(f'<text x="{x + 16}" y="{bottom + 40}">{name}</text>')
        x += 150
    out.append("</svg>")
    return "\n".join(out) + "\n"


def main(argv: list[str]) -> int:
    if len(argv) != 2:
        print(__doc__, file=sys.stderr)
        return 2
    with open(argv[0], encoding="utf-8") as handle:
        data = json.load(handle)
    with open(argv[1], "w", encoding="utf-8") as handle:
        handle.write(draw(data))
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
