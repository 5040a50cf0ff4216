"""A picture of a placement: robots, edge and cloud nodes as columns, every module instance in the
box of the node it runs on, a line from each robot to the nodes that serve it, and how full each
node is. Plain SVG, no dependencies; written beside the manifests as ``placement.svg``."""

from __future__ import annotations

from xml.sax.saxutils import escape

from .placement import Placement

TIERS = ("onboard", "edge", "cloud")
TITLES = {"onboard": "Robots (onboard)", "edge": "Edge", "cloud": "Cloud"}
PALETTE = ("#1f77b4", "#ff7f0e", "#2ca02c", "#d62728", "#9467bd", "#8c564b", "#e377c2", "#7f7f7f", "#bcbd22", "#17becf")
COLUMN_X = {"onboard": 20, "edge": 360, "cloud": 700}
BOX_WIDTH = 280
LINE = 15
TOP = 70
GAP = 14


def _fill(node: dict) -> float:
    parts = []
    if node["cpu_millis"]:
        parts.append(1 - max(node["free_cpu_millis"], 0) / node["cpu_millis"])
    if node["memory_bytes"]:
        parts.append(1 - max(node["free_memory_bytes"], 0) / node["memory_bytes"])
    return max(parts) if parts else 0.0


def render_placement_svg(placement: Placement) -> str:
    modules = sorted({inst.module for inst in placement.instances})
    color = {m: PALETTE[i % len(PALETTE)] for i, m in enumerate(modules)}
    contents: dict[str, list[tuple[str, str]]] = {n["name"]: [] for n in placement.nodes}
    for inst in sorted(placement.instances, key=lambda i: (i.module, i.robots)):
        serves = inst.robots[0] if len(inst.robots) == 1 else f"{len(inst.robots)} robots"
        contents.setdefault(inst.node, []).append((f"{inst.module} · {serves}", color[inst.module]))
    for fleet, servers in sorted(placement.discovery.items()):
        for server in servers:
            contents.setdefault(server.node, []).append((f"◆ discovery-{server.server_id} ({fleet})", "#444444"))

    boxes: dict[str, tuple[float, float, float]] = {}  # node -> x, y, height
    bottom = TOP
    for tier in TIERS:
        y = TOP
        for node in sorted((n for n in placement.nodes if n["tier"] == tier), key=lambda n: (n.get("fleet") or "", n["name"])):
            height = 44 + LINE * max(len(contents.get(node["name"], [])), 1)
            boxes[node["name"]] = (COLUMN_X[tier], y, height)
            y += height + GAP
        bottom = max(bottom, y)

    out = []
    width = COLUMN_X["cloud"] + BOX_WIDTH + 20
    height = bottom + 30 + LINE * ((len(modules) + 3) // 4)
    out.append(
        f'<svg xmlns="http://www.w3.org/2000/svg" width="{width}" height="{height}" viewBox="0 0 {width} {height}" '
        'font-family="DejaVu Sans, Helvetica, Arial, sans-serif" font-size="11">'
    )
    out.append(f'<rect width="{width}" height="{height}" fill="#ffffff"/>')
    names = ", ".join(sorted(d["name"] for d in placement.deployments))
    out.append(f'<text x="20" y="24" font-size="15" font-weight="bold">KubeROS placement: {escape(names)}</text>')
    for tier in TIERS:
        out.append(f'<text x="{COLUMN_X[tier]}" y="52" font-size="13" font-weight="bold">{TITLES[tier]}</text>')

    robot_node = {n["robot"]: n["name"] for n in placement.nodes if n["tier"] == "onboard"}
    for inst in placement.instances:
        if inst.tier == "onboard" or inst.node not in boxes:
            continue
        x2, y2, h2 = boxes[inst.node]
        for robot in inst.robots:
            if robot_node.get(robot) not in boxes:
                continue
            x1, y1, h1 = boxes[robot_node[robot]]
            sx, sy, ex, ey = x1 + BOX_WIDTH, y1 + h1 / 2, x2, y2 + h2 / 2
            mid = (sx + ex) / 2
            out.append(
                f'<path d="M{sx:.0f},{sy:.0f} C{mid:.0f},{sy:.0f} {mid:.0f},{ey:.0f} {ex:.0f},{ey:.0f}" '
                f'fill="none" stroke="{color[inst.module]}" stroke-opacity="0.45" stroke-width="1.5"/>'
            )

    for node in placement.nodes:
        if node["name"] not in boxes:
            continue
        x, y, h = boxes[node["name"]]
        fill = _fill(node)
        title = node["name"] + (f"  [{node['fleet']}]" if node.get("fleet") else "")
        capacity = f"{node['cpu_millis'] / 1000:g} CPU · {node['memory_bytes'] / 1024**3:g} GiB" + (
            f" · {node['gpu']} GPU" if node["gpu"] else ""
        )
        out.append(f"<g><title>{escape(node['name'])}: {fill:.0%} used</title>")
        out.append(f'<rect x="{x}" y="{y}" width="{BOX_WIDTH}" height="{h}" rx="6" fill="#f7f7f7" stroke="#999999"/>')
        out.append(f'<text x="{x + 8}" y="{y + 16}" font-weight="bold">{escape(title)}</text>')
        out.append(f'<text x="{x + 8}" y="{y + 30}" fill="#666666">{escape(capacity)}</text>')
        bar_width, bar_x = 70, x + BOX_WIDTH - 78
        bar_color = "#d62728" if fill > 0.9 else "#2ca02c"
        out.append(f'<rect x="{bar_x}" y="{y + 8}" width="{bar_width}" height="8" fill="#e0e0e0"/>')
        out.append(f'<rect x="{bar_x}" y="{y + 8}" width="{bar_width * min(fill, 1):.1f}" height="8" fill="{bar_color}"/>')
        out.append(f'<text x="{bar_x + bar_width}" y="{y + 30}" fill="#666666" text-anchor="end">{fill:.0%} used</text>')
        for index, (label, stroke) in enumerate(contents.get(node["name"], [])):
            ly = y + 46 + index * LINE
            out.append(f'<rect x="{x + 8}" y="{ly - 8}" width="8" height="8" fill="{stroke}"/>')
            out.append(f'<text x="{x + 22}" y="{ly}">{escape(label)}</text>')
        out.append("</g>")

    for index, module in enumerate(modules):
        lx = 20 + (index % 4) * 250
        ly = bottom + 14 + (index // 4) * LINE
        out.append(f'<rect x="{lx}" y="{ly - 8}" width="10" height="10" fill="{color[module]}"/>')
        out.append(f'<text x="{lx + 16}" y="{ly + 1}">{escape(module)}</text>')
    out.append("</svg>")
    return "\n".join(out) + "\n"
