"""Where every module of every robot runs: the one table format people read, for the three moments they read it.

- ``placement_table``: what the scheduler decided, with its reasons (render, ``place_modules``);
- ``compare`` + ``deploy_table``: what runs against what was placed, after a deploy (``rosdeployment``,
  ``rosdeployment_info``; the pods come from ``cluster_state.running_modules``);
- ``controller_table``: what the controller reports per record (version, phase, last move; ``reconcile.status_rows``).

Pure: plain rows in, text out.
"""

from __future__ import annotations

from .placement import Placement
from .validation import split_image


def format_table(header: tuple, rows: list[tuple]) -> str:
    """Fixed-width columns, two spaces apart; the last column is not padded and no line ends in spaces."""
    lines = [header, *rows]
    widths = [max(len(str(line[i])) for line in lines) for i in range(len(header) - 1)]
    return "\n".join(
        "  ".join([*(str(c).ljust(w) for c, w in zip(line, widths, strict=False)), str(line[-1])]).rstrip() for line in lines
    )


def placement_table(placement: Placement) -> str:
    """A fixed-width table of where every module of every robot runs, and the discovery servers."""
    header = ("DEPLOYMENT", "ROBOT", "MODULE", "TIER", "NODE", "REASON")
    rows = [(r["deployment"], r["robot"], r["module"], r["tier"], r["node"], r["reason"]) for r in placement.rows()]
    for fleet, servers in placement.discovery.items():
        for s in servers:
            rows.append((f"(fleet {fleet})", "-", s.name, s.tier, s.node, s.reason))
    for r in placement.robot_servers:
        rows.append((r.deployment, r.robot, "(discovery server)", "onboard", r.node, "the robot's own, for its onboard modules"))
    return format_table(header, rows)


# Waiting reasons of a container whose image the kubelet cannot get: they do not resolve by waiting.
IMAGE_PULL_REASONS = ("ErrImagePull", "ImagePullBackOff", "InvalidImageName", "ErrImageNeverPull")
_PULL_CAUSES = (
    (("401 unauthorized", "failed to authorize", "authentication required", "unauthorized"),
     "the registry refused the credentials (check the pull secret named in imageRegistries)"),
    (("403 forbidden", "denied"), "the registry denied access to it"),
    (("not found", "manifest unknown", "name unknown"), "the registry has no such image (check its name and digest)"),
    (("x509", "certificate"), "the node does not trust the registry's certificate (its container runtime needs the CA)"),
    (("connection refused", "no such host", "i/o timeout", "no route to host", "network is unreachable"),
     "the node cannot reach the registry"),
    (("errimageneverpull", "never pull"), "imagePullPolicy is Never and the node does not have it"),
    (("invalid reference", "invalidimagename", "couldn't parse image"), "the image name is not valid"),
)  # fmt: skip


def image_registry(image: str) -> str:
    """The registry an image reference names (Docker Hub when it names none), as validation reads references."""
    return split_image(image)[0] or "docker.io"


def image_pull_problem(image: str, reason: str, message: str) -> str:
    """One sentence for a container the kubelet cannot start because of its image: which image, which registry,
    and why in words a developer acts on (the kubelet's own message follows, shortened)."""
    text = f"{reason} {message}".lower()
    why = next((cause for needles, cause in _PULL_CAUSES if any(n in text for n in needles)), "the pull failed")
    detail = " ".join(message.split())
    if len(detail) > 300:
        detail = detail[:297] + "..."
    return f"image {image} from registry {image_registry(image)}: {why} ({reason}{': ' + detail if detail else ''})"


# Phases a pod never leaves; a Deployment replaces such a pod (evicted, shut down with its node) with a new one.
TERMINAL_PHASES = ("Succeeded", "Failed")
# Container waiting reasons that are the normal way to start, not a problem to report.
_STARTING = ("ContainerCreating", "PodInitializing")


def _short(text: str, limit: int = 240) -> str:
    text = " ".join(str(text).split())
    return text if len(text) <= limit else text[: limit - 3] + "..."


def is_ready(obj: dict) -> bool:
    """Whether a node or a pod (as the API server sends it) reports its Ready condition True."""
    return any(c.get("type") == "Ready" and c.get("status") == "True" for c in (obj.get("status") or {}).get("conditions") or [])


def pod_note(pod: dict) -> str:
    """Why a pod is not (yet) serving, in the cluster's own words ("" when nothing says): the scheduler's reason
    for a pod it cannot place (untolerated taints, resources), the reason a pod ended (Evicted and the resource the
    node ran low on, a node shutdown), a container waiting on something other than its start (CrashLoopBackOff)."""
    status = pod.get("status") or {}
    phase = status.get("phase")
    if phase in TERMINAL_PHASES:
        reason = status.get("reason") or phase
        return _short(f"{reason}: {status['message']}" if status.get("message") else f"ended ({reason})")
    for condition in status.get("conditions") or []:
        if condition.get("type") == "PodScheduled" and condition.get("status") == "False":
            return _short(f"not scheduled: {condition.get('message') or condition.get('reason') or 'no node fits'}")
    for container in (status.get("initContainerStatuses") or []) + (status.get("containerStatuses") or []):
        waiting = (container.get("state") or {}).get("waiting") or {}
        if waiting.get("reason") and waiting["reason"] not in _STARTING:
            last = ((container.get("lastState") or {}).get("terminated") or {}).get("exitCode")
            exited = f", last exit code {last}" if last is not None else ""
            return _short(f"container {container.get('name', '?')}: {waiting['reason']}{exited}")
    return ""


def _server_row(fleet: str, name: str, tier: str, node: str) -> dict:
    """A fleet's discovery or bridge server as a placed row."""
    return {"deployment": f"(fleet {fleet})", "fleet": fleet, "robot": "-", "module": name, "tier": tier, "node": node,
            "instance": name}  # fmt: skip


def _fleet_rows(placement: dict) -> list[dict]:
    """The placed rows of a placement's plain data, with each fleet's discovery and bridge servers."""
    wanted = list(placement["placements"])
    for entry in placement.get("discovery", []):
        wanted.extend(_server_row(entry["fleet"], s["name"], s["tier"], s["node"]) for s in entry["servers"])
    wanted.extend(_server_row(b["fleet"], b["name"], b["tier"], b["node"]) for b in placement.get("bridges", []))
    fleets = {d["name"]: d["fleet"] for d in placement.get("deployments", [])}
    for server in placement.get("robot_discovery", []):
        wanted.append(
            {"deployment": server["deployment"], "fleet": fleets.get(server["deployment"], ""), "robot": server["robot"],
             "module": "(discovery server)", "tier": "onboard", "node": server["node"], "instance": server["name"]}
        )  # fmt: skip
    return wanted


def compare(placement: dict, pods: list[dict]) -> list[dict]:
    """One row per placed (robot, module) and fleet server: where it was placed and where its pod runs."""
    by_instance: dict[tuple[str, str], list[dict]] = {}
    for pod in pods:
        by_instance.setdefault((pod["fleet"], pod["instance"]), []).append(pod)
    rows = []
    for row in _fleet_rows(placement):
        if row.get("cluster"):
            # Runs in a third-party cluster: applied and watched there, not here.
            rows.append(
                {"deployment": row["deployment"], "robot": row["robot"], "module": row["module"], "tier": row["tier"],
                 "placed_node": row["node"], "node": row["node"], "phase": "Remote", "ready": True, "pod": None,
                 "problem": "", "problem_final": False, "note": ""}
            )  # fmt: skip
            continue
        live = by_instance.get((row["fleet"], row["instance"]), [])
        # the ready pod, else one still on its way (an ended pod is history its Deployment has replaced)
        pod = next((p for p in live if p["ready"]), None) or next((p for p in live if p["phase"] not in TERMINAL_PHASES), None)
        pod = pod or (live[0] if live else None)
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
                "problem": (pod or {}).get("problem", ""),
                "problem_final": bool((pod or {}).get("problem_final")),
                "note": (pod or {}).get("note", ""),
            }
        )
    return rows


def deploy_table(rows: list[dict]) -> str:
    """The table a deploy prints: every row of ``compare``."""
    header = ("DEPLOYMENT", "ROBOT", "MODULE", "TIER", "NODE (CLUSTER)", "PHASE", "PLACED ON")
    return format_table(
        header,
        [
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
        ],
    )


def controller_table(deployment: str, rows: list[dict]) -> str:
    """The table of the controller's status ConfigMap: one record's rows (``reconcile.status_rows``)."""
    header = ("ROBOT", "MODULE", "VERSION", "NODE", "PHASE", "LAST MOVE")
    lines = []
    for r in rows:
        move = r["last_move"]
        text = f"{move['at']} from {move['from']}: {move['why']}" if move else ""
        if r["note"]:
            text = (text + "; " if text else "") + r["note"]
        lines.append((r["robot"], r["module"], r.get("version", "") or "-", r["node"], r["phase"], text))
    return f"RosDeployment {deployment}\n" + format_table(header, lines)
