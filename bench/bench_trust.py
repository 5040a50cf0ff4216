#!/usr/bin/env python3
"""Trust benchmark: the worst inputs an attacker can hand the collection, measured on this checkout and, side by side
in the same run, on an earlier commit (``--before``, default the commit before the trust work), so the figures are a
ratio on one machine and not two noisy runs.

Each measurement runs in a fresh Python child whose ``PYTHONPATH`` puts that tree's collection first (the generators
come from this checkout's tests/ either way):

- **topics bomb** (tests/topics_bomb.py: 100 modules sharing one declared-topics block by YAML aliases, 100 topics
  each way, about 13 KB): ``load_rosdeployments`` refuses it; wall time of the call, the child's peak RSS
  (``os.wait4``), and the number of lines of the refusal.
- **registry huge body**: a token service answering 200 MB (no Content-Length) to ``manifest_digest``; the child's
  tracemalloc peak during the call (what the answer made the client hold).
- **registry trickle**: a registry answering one byte every 0.2 s; seconds until ``check()`` returns or fails,
  stopped at ``--trickle-stop`` seconds (then reported as that figure, and ``registry_trickle_stopped``); the
  client's own deadline is its default (``registry_api.DEADLINE_S``, 60 s).
- **credentials sent elsewhere**: Basic credentials that reached a host they were not given for, over three
  scenarios: a token realm on another host, a realm redirecting to another host, a mirror without a login of its
  own (tests/hostile_registry.py records every request's Authorization).
- **redaction**: ``--cases`` generated logs (tests/redaction_cases.py: PEM and PGP keys, Basic auth, URL passwords,
  cloud keys, header tokens, Secret values in their encodings) cut into follow windows; each window redacted as the
  tree does it (its ``Redactor`` fed window after window, else ``redact`` per window); a leak is a forbidden piece
  shown.

    .venv/bin/python bench/bench_trust.py                  # results/trust.json, Markdown on stdout
    .venv/bin/python bench/bench_trust.py --before none    # this checkout only
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
BEFORE = "cfacb84"  # the last commit before the trust work (issue 44)
sys.path[:0] = [str(REPO / "bench"), str(REPO / "tests"), str(REPO / ".collections")]

CHILD = r"""
import json, os, sys, time, tracemalloc
probe, args = sys.argv[1], json.loads(sys.argv[2])
P = "ansible_collections.kuberos.platform.plugins.module_utils."
out = {}
if probe == "topics":
    from topics_bomb import bomb_spec
    from importlib import import_module
    spec = import_module(P + "kuberos.spec")
    errors = import_module(P + "kuberos.errors")
    text = bomb_spec(100, 100)
    started = time.perf_counter()
    try:
        spec.load_rosdeployments(text, "bomb.yml")
        message = ""
    except errors.SpecError as exc:
        message = str(exc)
    out = {"s": time.perf_counter() - started, "lines": len(message.splitlines()), "bytes": len(message)}
elif probe in ("huge", "trickle"):
    from importlib import import_module
    api = import_module(P + "kuberos_deploy.registry_api")
    tracemalloc.start()
    started = time.perf_counter()
    client = api.RegistryApi(args["address"], "alice", "s3cret", args["ca_file"])
    try:
        client.manifest_digest("app", "1.0") if probe == "huge" else client.check()
        outcome = "answered"
    except Exception as exc:
        outcome = f"{type(exc).__name__}: {str(exc)[:200]}"
    out = {"s": time.perf_counter() - started, "peak_mib": tracemalloc.get_traced_memory()[1] / 2**20, "outcome": outcome}
elif probe == "credentials":
    from importlib import import_module
    api = import_module(P + "kuberos_deploy.registry_api")
    digests = import_module(P + "kuberos_deploy.image_digests")
    outcomes = []
    for scenario in args["scenarios"]:
        try:
            if scenario == "mirror":
                mirrors = {"ghcr.io": [{"url": "https://" + args["address"], "ca": args["ca_file"]}]}
                digests.resolve(["ghcr.io/app:1.0"], mirrors, {"ghcr.io": ("alice", "s3cret")})
            else:
                api.RegistryApi(args["address"], "alice", "s3cret", args["ca_file"]).manifest_digest(scenario, "1.0")
            outcomes.append("answered")
        except Exception as exc:
            outcomes.append(f"{type(exc).__name__}: {str(exc)[:160]}")
    out = {"outcomes": outcomes}
elif probe == "redaction":
    from importlib import import_module
    logs = import_module(P + "kuberos.module_logs")
    stateful = hasattr(logs, "Redactor")
    if not stateful:  # an earlier tree: the generators import the name, the probe redacts window by window
        logs.Redactor = None
    from redaction_cases import cases
    leaked = shown_cases = 0
    started = time.perf_counter()
    generated = cases(args["cases"], args["seed"])
    for windows, secrets, forbidden in generated:
        if stateful:
            redactor = logs.Redactor(secrets)
            shown = "\n".join(redactor.redact(w) for w in windows)
        else:
            shown = "\n".join(logs.redact(w, secrets) for w in windows)
        found = [piece for piece in forbidden if piece in shown]
        leaked += bool(found)
        shown_cases += 1
    out = {"cases": shown_cases, "leaks": leaked, "s": time.perf_counter() - started}
print(json.dumps(out))
"""


def child(tree: Path, probe: str, args: dict, stop_s: float = 600.0) -> dict:
    """Run ``probe`` in a fresh Python with ``tree``'s collection first: its answer and wall time (stopped at ``stop_s``)."""
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(tree / ".collections"), str(REPO / "tests")])}
    started = time.monotonic()
    process = subprocess.Popen([sys.executable, "-c", CHILD, probe, json.dumps(args)], env=env, stdout=subprocess.PIPE,
                               stderr=subprocess.PIPE, text=True)  # fmt: skip
    try:
        stdout, stderr = process.communicate(timeout=stop_s)
        stopped = False
    except subprocess.TimeoutExpired:
        process.kill()
        stdout, stderr = process.communicate()
        stopped = True
    wall = time.monotonic() - started
    if stopped:
        return {"stopped": True, "wall_s": wall}
    if process.returncode != 0:
        raise SystemExit(f"{probe} on {tree} failed:\n{stderr[-3000:]}")
    return {**json.loads(stdout.strip().splitlines()[-1]), "wall_s": wall}


def peak_rss(tree: Path, probe: str, args: dict) -> float:
    """The peak RSS (MiB) of one child alone (os.wait4 of that child, not the largest so far)."""
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(tree / ".collections"), str(REPO / "tests")])}
    process = subprocess.Popen([sys.executable, "-c", CHILD, probe, json.dumps(args)], env=env,
                               stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)  # fmt: skip
    _pid, _status, usage = os.wait4(process.pid, 0)
    return usage.ru_maxrss / 1024


def worktree(commit: str, folder: str) -> Path:
    """A checkout of ``commit`` with its own collection path (the earlier code, imported as the collection)."""
    path = Path(folder) / "before"
    subprocess.run(["git", "-C", str(REPO), "worktree", "add", "--detach", "-q", str(path), commit], check=True)
    link = path / ".collections" / "ansible_collections" / "kuberos" / "platform"
    if not link.exists():
        link.parent.mkdir(parents=True, exist_ok=True)
        link.symlink_to("../../..")
    return path


def measure(tree: Path, cases: int, trickle_stop: float) -> dict:
    from hostile_registry import HostileRegistry, huge, manifest, manifest_basic, redirect_to, token, trickle

    result = {}
    topics = child(tree, "topics", {})
    result["topics_bomb_s"] = round(topics["s"], 3)
    result["topics_bomb_lines"] = topics["lines"]
    result["topics_bomb_text_bytes"] = topics["bytes"]
    result["topics_bomb_peak_mib"] = round(peak_rss(tree, "topics", {}), 1)
    with tempfile.TemporaryDirectory() as folder, HostileRegistry(folder) as server:
        args = {"address": server.address, "ca_file": server.ca_file}
        server.realm = server.url("127.0.0.1", "/token")
        server.routes = {"/v2/app/manifests/1.0": manifest, "/token": huge(200 * 1024 * 1024)}
        big = child(tree, "huge", args)
        result["registry_huge_body_peak_mib"] = round(big["peak_mib"], 1)
        result["registry_huge_body_outcome"] = big["outcome"]
        server.routes = {"/v2/": trickle(0.2, trickle_stop + 30)}
        slow = child(tree, "trickle", args, stop_s=trickle_stop)
        result["registry_trickle_s"] = round(slow.get("s", slow["wall_s"]), 2)
        result["registry_trickle_stopped"] = bool(slow.get("stopped"))
        result["registry_trickle_outcome"] = slow.get("outcome", f"still reading after {trickle_stop:g} s (stopped)")
        server.requests.clear()
        server.routes = {
            "/v2/realm-elsewhere/manifests/1.0": manifest, "/token-elsewhere": token,
            "/v2/realm-redirect/manifests/1.0": manifest, "/token-redirect": redirect_to(server.url("localhost", "/stolen")),
            "/stolen": token, "/v2/app/manifests/1.0": manifest_basic,
        }  # fmt: skip
        sent = {}
        for scenario, realm in (("realm-elsewhere", server.url("localhost", "/token-elsewhere")),
                                ("realm-redirect", server.url("127.0.0.1", "/token-redirect")), ("mirror", "")):  # fmt: skip
            server.realm = realm
            before = len(server.requests)
            child(tree, "credentials", {**args, "scenarios": [scenario]})
            fresh = server.requests[before:]
            if scenario == "mirror":  # the mirror (127.0.0.1) was given no login: any Basic it got is the upstream's
                sent[scenario] = sum(1 for _m, _h, _p, auth in fresh if (auth or "").startswith("Basic "))
            else:  # only 127.0.0.1 was given the credentials
                sent[scenario] = sum(1 for _m, h, _p, auth in fresh if h == "localhost" and (auth or "").startswith("Basic "))
        result["credentials_sent_elsewhere"] = sum(sent.values())
        result["credentials_sent_elsewhere_by_scenario"] = sent
    redaction = child(tree, "redaction", {"cases": cases, "seed": 44})
    result["redaction_cases"] = redaction["cases"]
    result["redaction_leaks"] = redaction["leaks"]
    result["redaction_s"] = round(redaction["s"], 2)
    return result


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--before", default=BEFORE, help="an earlier commit to measure side by side ('none': skip)")
    parser.add_argument("--cases", type=int, default=2000, help="generated logs for the redaction count")
    parser.add_argument("--trickle-stop", type=float, default=120.0, help="seconds after which a trickled read is stopped")
    parser.add_argument("--json", default=str(REPO / "bench" / "results" / "trust.json"))
    arguments = parser.parse_args()
    from bench_deploy import machine

    after = measure(REPO, arguments.cases, arguments.trickle_stop)
    before = None
    if arguments.before != "none":
        with tempfile.TemporaryDirectory(prefix="kuberos-trust-before-") as folder:
            tree = worktree(arguments.before, folder)
            try:
                before = measure(tree, arguments.cases, arguments.trickle_stop)
            finally:
                subprocess.run(["git", "-C", str(REPO), "worktree", "remove", "--force", str(tree)], check=False)
    result = {**after, "before": before, "before_commit": arguments.before, "machine": machine(),
              "command": " ".join(["bench/bench_trust.py", *sys.argv[1:]])}  # fmt: skip
    Path(arguments.json).write_text(json.dumps(result, indent=2, sort_keys=True) + "\n")
    keys = [k for k in after if not k.endswith(("_outcome", "_by_scenario"))]
    print(f"| figure | {arguments.before} (before) | {result['machine']['commit']} (now) |\n|---|---|---|")
    for key in keys:
        print(f"| {key} | {before.get(key) if before else ''} | {after[key]} |")
    return 0 if after["credentials_sent_elsewhere"] == 0 and after["redaction_leaks"] == 0 else 1


if __name__ == "__main__":
    raise SystemExit(main())
