#!/usr/bin/env python3
"""Dashboard and /metrics benchmark: what the controller's dashboard costs and how fast it answers at N robots.

On a dedicated local control plane (bench_deploy's: one kwok node per robot, 20 edge and 10 cloud nodes) the
pick-and-place app is deployed with ``playbooks/deploy.yml`` to N robots (4 dedicated modules each: 4·N pods plus 2
discovery servers). Then, side by side in one run:

- the controller alone (``--dashboard-port 0``) and the controller serving the dashboard run for ``--idle`` seconds
  each: their resident memory and CPU seconds, and the ratios (dashboard / alone);
- the view: the time of one build over every watched object (``build_s`` from ``/api/summary``, after each of
  ``--changes`` changes) and the time from a change in the cluster (an annotation on a robot's node) to a new view
  generation seen on ``/api/summary`` (the page hears of it on its stream at that moment);
- ``/metrics``: the time of a scrape (median of ``--scrapes``), its size and number of series;
- the JSON behind the pages: ``/api/summary``, a page of 100 modules, a search, the resources page;
- the first paint in a headless Chromium: a fresh page load until the first view is drawn, measured in the page
  (``performance.now()`` at the first render, from the navigation's start), median of ``--loads`` loads of the
  deployments view, and one load of every other view. Target: under 1 s at 1,000 robots.

Output: Markdown on stdout (progress on stderr) and ``bench/results/dashboard-<N>.json``.

    .venv/bin/python bench/bench_dashboard.py --robots 1000
    .venv/bin/python bench/bench_dashboard.py --robots 20 --idle 10   # smoke run

The cluster is stopped and its state removed at the end unless ``--keep-cluster``.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import socket
import statistics
import subprocess
import sys
import tempfile
import time
import urllib.request
from pathlib import Path

from bench_deploy import (
    DISCOVERY_SERVERS,
    MODULES_PER_ROBOT,
    REPO,
    RESULTS_DIR,
    VENV_BIN,
    Cluster,
    check,
    machine,
    playbook,
    wait_all_ready,
    write_inventory,
    write_spec,
)

ENTRY = "ansible_collections.kuberos.platform.plugins.module_utils.kuberos_controller"
VIEWS = ("deployments", "resources", "fleets", "software", "events", "map")
FIRST_PAINT_TARGET_S = 1.0


def log(message: str) -> None:
    print(f"[{time.strftime('%H:%M:%S')}] {message}", file=sys.stderr, flush=True)


def free_port() -> int:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return probe.getsockname()[1]


def get(url: str) -> tuple[float, bytes]:
    started = time.perf_counter()
    with urllib.request.urlopen(url, timeout=60) as response:
        body = response.read()
    return time.perf_counter() - started, body


class Controller:
    """One controller process (no leader election), with or without its dashboard."""

    def __init__(self, kubeconfig: Path, workdir: Path, port: int):
        self.port = port
        self.log_path = workdir / f"controller-{port or 'alone'}.log"
        env = {**os.environ, "PYTHONPATH": str(REPO / ".collections")}
        command = [str(VENV_BIN / "python"), "-m", ENTRY, "--kubeconfig", str(kubeconfig), "--no-leader-elect",
                   "--dashboard-port", str(port), "--log-level", "WARNING"]  # fmt: skip
        self.log = open(self.log_path, "w", encoding="utf-8")
        self.process = subprocess.Popen(command, env=env, stdout=self.log, stderr=subprocess.STDOUT)
        self.base = f"http://127.0.0.1:{port}"

    def rss_mib(self) -> float:
        with open(f"/proc/{self.process.pid}/status", encoding="utf-8") as handle:
            line = next(line for line in handle if line.startswith("VmRSS:"))
        return int(line.split()[1]) / 1024

    def cpu_s(self) -> float:
        with open(f"/proc/{self.process.pid}/stat", encoding="utf-8") as handle:
            fields = handle.read().rsplit(")", 1)[1].split()
        return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")

    def summary(self) -> dict:
        return json.loads(get(self.base + "/api/summary")[1])

    def wait_view(self, rows: int, timeout: float) -> float:
        started = time.monotonic()
        while time.monotonic() < started + timeout:
            try:
                if self.summary()["rows"] == rows:
                    return time.monotonic() - started
            except OSError:
                pass
            time.sleep(0.1)
        raise SystemExit(f"bench: the dashboard never showed {rows} rows; log {self.log_path}")

    def stop(self) -> None:
        self.process.terminate()
        try:
            self.process.wait(15)
        except subprocess.TimeoutExpired:
            self.process.kill()
        self.log.close()


def idle_cost(controller: Controller, seconds: float) -> dict:
    cpu = controller.cpu_s()
    time.sleep(seconds)
    return {"rss_mib": round(controller.rss_mib(), 1), "cpu_s": round(controller.cpu_s() - cpu, 2), "seconds": seconds}


def median_ms(values: list[float]) -> float:
    return round(statistics.median(values) * 1000, 1)


def measure_change(cluster: Cluster, controller: Controller, robots: int, changes: int) -> dict:
    """Annotate a robot's node ``changes`` times; each time, how long until a new view generation is served."""
    core = cluster.core()
    delays, builds = [], []
    for i in range(changes):
        before = controller.summary()["generation"]
        name = f"robot-{(i * 37) % robots:03d}"
        started = time.perf_counter()
        core.patch_node(name, {"metadata": {"annotations": {"bench.kuberos.io/touch": str(time.time())}}})
        while time.perf_counter() < started + 30:
            summary = controller.summary()
            if summary["generation"] > before:
                delays.append(time.perf_counter() - started)
                builds.append(summary["build_s"])
                break
            time.sleep(0.01)
        time.sleep(1.0)
    return {"change_to_view_ms_median": median_ms(delays), "change_to_view_ms_max": round(max(delays) * 1000, 1),
            "build_ms_median": median_ms(builds), "changes": len(delays)}  # fmt: skip


def measure_http(controller: Controller, scrapes: int) -> dict:
    metrics = [get(controller.base + "/metrics") for _ in range(scrapes)]
    text = metrics[-1][1].decode()
    series = sum(1 for line in text.splitlines() if line and not line.startswith("#"))
    api = {}
    for name, path in (
        ("summary", "/api/summary"),
        ("modules_page", "/api/modules?size=100"),
        ("modules_search", "/api/modules?q=robot-9&phase=Running"),
        ("resources_page", "/api/resources?size=100"),
        ("events", "/api/events"),
        ("fleets", "/api/fleets"),
        ("software", "/api/software"),
        ("placement_svg", "/api/placement.svg"),
    ):
        timings = [get(controller.base + path) for _ in range(10)]
        api[name] = {"ms_median": median_ms([t for t, _ in timings]), "bytes": len(timings[-1][1])}
    return {"metrics_ms_median": median_ms([t for t, _ in metrics]), "metrics_bytes": len(metrics[-1][1]),
            "metrics_series": series, "api": api}  # fmt: skip


def measure_paint(base: str, loads: int) -> dict:
    from selenium import webdriver
    from selenium.webdriver.chrome.service import Service

    options = webdriver.ChromeOptions()
    for argument in ("--headless=new", "--no-sandbox", "--disable-gpu", "--disable-dev-shm-usage", "--window-size=1400,900"):
        options.add_argument(argument)
    options.binary_location = shutil.which("chromium")
    driver = webdriver.Chrome(service=Service(shutil.which("chromedriver")), options=options)

    def paint(view: str) -> float:
        driver.get("about:blank")
        driver.get(f"{base}/#{view}")
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline:
            painted = driver.execute_script("return document.body && document.body.dataset.firstPaintMs")
            if painted:
                return int(painted) / 1000
            time.sleep(0.02)
        raise SystemExit(f"bench: the {view} view never painted")

    try:
        paint("deployments")  # the browser's own start-up is not the page's
        first = [paint("deployments") for _ in range(loads)]
        views = {view: round(paint(view) * 1000) for view in VIEWS}
    finally:
        driver.quit()
    return {"first_paint_ms_median": median_ms(first), "first_paint_ms_max": round(max(first) * 1000), "loads": loads,
            "first_paint_ms_by_view": views}  # fmt: skip


def markdown(data: dict) -> str:
    m, alone, served = data["machine"], data["alone"], data["dashboard"]
    http, change, paint = data["http"], data["change"], data["paint"]
    lines = [
        f"### Dashboard and /metrics at {data['robots']} robots ({data['nodes']} nodes, {data['pods']} pods)",
        "",
        f"{m['date']}, {m['nproc']} cores ({m['cpu']}), {m['memory']}, commit {m['commit']}, load at start {data['load_start']}.",
        "",
        "| measure | value |",
        "|---|---|",
        f"| first paint, deployments view (median of {paint['loads']} loads; max) | {paint['first_paint_ms_median']:.0f} ms "
        f"({paint['first_paint_ms_max']} ms) |",
        "| first paint, each view | " + ", ".join(f"{k} {v} ms" for k, v in paint["first_paint_ms_by_view"].items()) + " |",
        f"| a change in the cluster to a new view (median; max) | {change['change_to_view_ms_median']:.0f} ms "
        f"({change['change_to_view_ms_max']:.0f} ms) |",
        f"| one view build over every object (median) | {change['build_ms_median']:.0f} ms |",
        f"| /metrics scrape (median) | {http['metrics_ms_median']:.0f} ms, {http['metrics_bytes'] / 1024:.0f} KiB, "
        f"{http['metrics_series']} series |",
        *(f"| GET {name} (median) | {v['ms_median']:.1f} ms, {v['bytes'] / 1024:.1f} KiB |" for name, v in http["api"].items()),
        f"| controller alone: memory, CPU over {alone['seconds']:.0f} s idle | {alone['rss_mib']} MiB, {alone['cpu_s']} s |",
        f"| controller with dashboard: memory, CPU over {served['seconds']:.0f} s idle | {served['rss_mib']} MiB, "
        f"{served['cpu_s']} s |",
        f"| ratio memory (dashboard / alone) | {data['ratio_rss']:.2f} |",
        "",
        f"First paint target (< {FIRST_PAINT_TARGET_S * 1000:.0f} ms at 1,000 robots): "
        + ("PASS" if paint["first_paint_ms_median"] < FIRST_PAINT_TARGET_S * 1000 else "FAIL"),
    ]
    return "\n".join(lines)


def parse_args(argv=None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--robots", type=int, default=1000)
    parser.add_argument("--idle", type=float, default=30.0, help="seconds each controller runs for the memory and CPU figures")
    parser.add_argument("--changes", type=int, default=5, help="cluster changes timed to a new view")
    parser.add_argument("--scrapes", type=int, default=10)
    parser.add_argument("--loads", type=int, default=5, help="page loads timed in the browser")
    parser.add_argument("--timeout", type=float, default=900)
    parser.add_argument("--keep-cluster", action="store_true")
    parser.add_argument("--results", type=Path, default=None)
    return parser.parse_args(argv)


def main(argv=None) -> int:
    args = parse_args(argv)
    work = Path(tempfile.mkdtemp(prefix="bench-dashboard-"))
    inventory = write_inventory(work / "inventory", args.robots)
    spec = write_spec(work / "spec.json")
    cluster = Cluster(inventory, work / "cluster", args.timeout)
    data = {"robots": args.robots, "machine": machine(), "load_start": " ".join(open("/proc/loadavg").read().split()[:3])}
    expected = args.robots * MODULES_PER_ROBOT + DISCOVERY_SERVERS
    controllers: list[Controller] = []
    try:
        log(f"starting a cluster of {args.robots} robots")
        cluster.start()
        log("deploying")
        started = time.monotonic()
        deployed = playbook(
            "deploy.yml", inventory, "-e", f"rosdeployment_file={spec}", "-e", f"kuberos_render_dir={work / 'render'}",
            "-e", f"kuberos_kubeconfig={cluster.kubeconfig}", "-e", f"rosdeployment_wait_timeout={int(args.timeout)}",
            timeout=args.timeout + 120,
        )  # fmt: skip
        check(deployed, "deploy.yml")
        core = cluster.core()
        if wait_all_ready(core, expected, started, started + args.timeout) is None:
            raise SystemExit("bench: the pods never became Ready")
        data["nodes"] = len(core.list_node().items)
        data["pods"] = expected
        log("the controller alone")
        alone = Controller(cluster.kubeconfig, work, 0)
        controllers.append(alone)
        time.sleep(10)  # its first list and pass
        data["alone"] = idle_cost(alone, args.idle)
        alone.stop()
        log("the controller with its dashboard")
        served = Controller(cluster.kubeconfig, work, free_port())
        controllers.append(served)
        data["first_view_s"] = round(served.wait_view(args.robots * MODULES_PER_ROBOT, args.timeout), 2)
        time.sleep(max(0.0, 10 - data["first_view_s"]))
        data["dashboard"] = idle_cost(served, args.idle)
        data["ratio_rss"] = data["dashboard"]["rss_mib"] / data["alone"]["rss_mib"]
        log("changes to views")
        data["change"] = measure_change(cluster, served, args.robots, args.changes)
        log("/metrics and the JSON")
        data["http"] = measure_http(served, args.scrapes)
        log("first paint in chromium")
        data["paint"] = measure_paint(served.base, args.loads)
        data["load_end"] = " ".join(open("/proc/loadavg").read().split()[:3])
        data["command"] = "bench/bench_dashboard.py " + " ".join(argv if argv is not None else sys.argv[1:])
        results = args.results or RESULTS_DIR / f"dashboard-{args.robots}.json"
        results.write_text(json.dumps(data, indent=2) + "\n")
        print(markdown(data))
        log(f"results in {results}")
    finally:
        for controller in controllers:
            if controller.process.poll() is None:
                controller.stop()
        if not args.keep_cluster:
            cluster.stop()
            shutil.rmtree(work, ignore_errors=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
