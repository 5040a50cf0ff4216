"""KubeROS-Bridge benchmark: latency and throughput through the bridge versus direct DDS, in one run.

Two network namespaces, "a" and "b", on one Linux bridge (tests/integration/test_discovery_netns.Lab),
stand for two hosts. Each runs a Fast DDS discovery server. Every process has a private /dev/shm and
uses UDP (FASTDDS_BUILTIN_TRANSPORTS=UDPv4), as pods on different nodes would.

- direct: a publisher in a and a subscriber in b in one ROS 2 graph (both name a's discovery server);
- bridge: the publisher in graph a, the bridge server in a, the bridge client in b, the subscriber in
  graph b (b's discovery server), the bridge over TCP between the namespaces with mutual TLS.

The publisher sends std_msgs/UInt8MultiArray messages of 1 KB and 1 MB, serialized once, with its send
time (CLOCK_REALTIME, shared by the namespaces) and a sequence number written into the payload; the
subscriber takes them raw (no Python message conversion on either end, in both paths) and computes the
one-way latency of every message. Latency phases run at a low fixed rate (1 KB: 200/s, 1 MB: 10/s);
rate phases offer 1 KB at 5,000/s and 10,000/s for 5 s; flood phases publish as fast as the publisher can
for 5 s. msgs/s is what arrived divided by the time from the first to the last arrival.
QoS: reliable, volatile, KEEP_LAST 100.

Run as root: .venv/bin/python bench/bench_bridge.py [--quick] [--append bench/RESULTS.md] [--json FILE]
(KUBEROS_BENCH_ONLY=name,name runs only those phases; KUBEROS_BENCH_KEEP=1 keeps the logs in /tmp.)
Every phase is bounded in messages and seconds; the namespaces and processes are removed at the end.
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import platform
import shutil
import signal
import statistics
import struct
import subprocess
import sys
import tempfile
import time

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
TOPIC = "/bench/a2b"
TYPE = "std_msgs/msg/UInt8MultiArray"
DEPTH = 100
HEADER = 16  # UInt8MultiArray CDR: encapsulation, empty dim sequence, data_offset, data length; then the data
STAMP = struct.Struct("<qqq")  # send time (ns), sequence, phase index; at the start of the data
BRIDGE = "ansible_collections.kuberos.platform.plugins.module_utils.kuberos_bridge"


# --- the ROS 2 ends (run inside the namespaces) -----------------------------------------------------------


def qos():
    from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

    return QoSProfile(
        history=HistoryPolicy.KEEP_LAST, depth=DEPTH, reliability=ReliabilityPolicy.RELIABLE,
        durability=DurabilityPolicy.VOLATILE,
    )  # fmt: skip


def executor(context):
    try:
        from rclpy.experimental import EventsExecutor

        return EventsExecutor(context=context)
    except ImportError:
        from rclpy.executors import SingleThreadedExecutor

        return SingleThreadedExecutor(context=context)


def publisher_main(args) -> None:
    """Warm up until the go file exists, then run the phases named in args.phases (JSON), then exit."""
    import rclpy
    from rclpy.serialization import serialize_message
    from std_msgs.msg import UInt8MultiArray

    rclpy.init()
    node = rclpy.create_node("kuberos_bench_pub")
    publisher = node.create_publisher(UInt8MultiArray, TOPIC, qos())
    phases = json.loads(args.phases)
    sizes = {1024} | {p["size"] for p in phases}
    templates = {size: bytearray(serialize_message(UInt8MultiArray(data=bytes(size)))) for size in sizes}
    assert all(len(t) == HEADER + size for size, t in templates.items())

    current = {"phase": -1}  # -1: warm-up

    def send(size: int, sequence: int) -> None:
        data = templates[size]
        STAMP.pack_into(data, HEADER, time.time_ns(), sequence, current["phase"])
        publisher.publish(bytes(data))

    deadline = time.monotonic() + args.warmup_timeout
    while not os.path.exists(args.go) and time.monotonic() < deadline:
        send(1024, -1)  # warm-up: the subscriber says it got one; nothing is measured
        time.sleep(0.1)
    print("go", flush=True)
    for index, phase in enumerate(phases):
        current["phase"] = index
        size, started = phase["size"], time.monotonic()
        if phase["kind"] == "latency":
            period = 1.0 / phase["rate"]
            for sequence in range(phase["count"]):
                send(size, sequence)
                next_at = started + (sequence + 1) * period
                time.sleep(max(0.0, next_at - time.monotonic()))
        elif phase["kind"] == "rate":  # a steady offered load: what is due every half millisecond
            sequence = 0
            while sequence < phase["count"] and time.monotonic() - started < phase["seconds"]:
                due = min(phase["count"], int((time.monotonic() - started) * phase["rate"]))
                while sequence < due:
                    send(size, sequence)
                    sequence += 1
                time.sleep(0.0005)
        else:  # flood: as fast as the publisher can
            sequence = 0
            while sequence < phase["count"] and time.monotonic() - started < phase["seconds"]:
                send(size, sequence)
                sequence += 1
        print(f"phase {phase['name']} published {sequence + 1 if phase['kind'] == 'latency' else sequence}", flush=True)
        time.sleep(phase.get("pause", 2.0))  # the path drains before the next phase
    print("done", flush=True)
    node.destroy_node()
    rclpy.shutdown()


def subscriber_main(args) -> None:
    """Record (receive time - send time, size, receive time, sequence) per message and phase, until the stop file."""
    import rclpy
    from std_msgs.msg import UInt8MultiArray

    rclpy.init()
    node = rclpy.create_node("kuberos_bench_sub")
    phases: list[list] = [[] for _ in range(int(args.phases))]
    state = {"warm": False}

    def received(data: bytes) -> None:
        now = time.time_ns()
        sent, sequence, phase = STAMP.unpack_from(data, HEADER)
        if sequence == -1:
            if not state["warm"]:
                state["warm"] = True
                print("warm", flush=True)
        elif 0 <= phase < len(phases):
            phases[phase].append((now - sent, len(data) - HEADER, now, sequence))

    node.create_subscription(UInt8MultiArray, TOPIC, received, qos(), raw=True)
    spinner = executor(rclpy.get_default_context())
    spinner.add_node(node)
    print("ready", flush=True)
    deadline = time.monotonic() + args.timeout
    while not os.path.exists(args.stop) and time.monotonic() < deadline:
        spinner.spin_once(timeout_sec=0.1)
    with open(args.out, "w", encoding="utf-8") as handle:
        json.dump(phases, handle)
    print("saved", flush=True)


# --- the orchestration (root, host namespace) -------------------------------------------------------------


class Runner:
    def __init__(self, lab, directory: str):
        sys.path[:0] = [os.path.join(ROOT, ".collections")]
        from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_lab.ros_wheels import PRIVATE_SHM, ros_environment

        self.lab, self.directory, self.shm = lab, directory, PRIVATE_SHM
        self.env = ros_environment(log_dir=os.path.join(directory, "ros-log"))
        self.env["PYTHONPATH"] = os.path.join(ROOT, ".collections")
        self.env["FASTDDS_BUILTIN_TRANSPORTS"] = "UDPv4"
        self.env["RMW_IMPLEMENTATION"] = "rmw_fastrtps_cpp"
        self.procs: list[tuple[str, subprocess.Popen, str]] = []

    def graph(self, role: str) -> dict[str, str]:
        return {"ROS_DISCOVERY_SERVER": f"{self.lab.addresses[role]}:11811"}

    def start(self, name: str, role: str, command: list[str], env: dict | None = None) -> str:
        log = os.path.join(self.directory, f"{name}.log")
        with open(log, "wb") as out:
            popen = subprocess.Popen(
                ["ip", "netns", "exec", self.lab.namespaces[role], "sh", "-c", self.shm, "sh", *command],
                env={**self.env, **(env or {})}, stdin=subprocess.DEVNULL, stdout=out, stderr=subprocess.STDOUT,
                start_new_session=True,
            )  # fmt: skip
        self.procs.append((name, popen, log))
        return log

    @staticmethod
    def text(log: str) -> str:
        with open(log, encoding="utf-8", errors="replace") as handle:
            return handle.read()

    def wait_for(self, log: str, word: str, timeout: float) -> None:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if word in self.text(log):
                return
            time.sleep(0.1)
        raise RuntimeError(f"{os.path.basename(log)}: no {word!r} within {timeout:.0f} s:\n{self.text(log)[-3000:]}")

    def stop(self, name: str) -> None:
        for proc_name, popen, _ in self.procs:
            if proc_name == name and popen.poll() is None:
                os.killpg(popen.pid, signal.SIGTERM)
                try:
                    popen.wait(15)
                except subprocess.TimeoutExpired:
                    os.killpg(popen.pid, signal.SIGKILL)
                    popen.wait(5)

    def close(self) -> None:
        for name, _, _ in reversed(self.procs):
            self.stop(name)


def run_path(runner: Runner, path: str, phases: list[dict], timeout: float) -> list[list]:
    """One publisher and one subscriber through ``path`` (direct or bridge); the samples of every phase."""
    go = os.path.join(runner.directory, f"go-{path}")
    out = os.path.join(runner.directory, f"samples-{path}.json")
    sub_graph = runner.graph("a" if path == "direct" else "b")
    stop = os.path.join(runner.directory, f"stop-{path}")
    sub = runner.start(
        f"sub-{path}", "b",
        [sys.executable, __file__, "_sub", "--phases", str(len(phases)), "--out", out, "--timeout", str(timeout),
         "--stop", stop],
        sub_graph,
    )  # fmt: skip
    runner.wait_for(sub, "ready", 60)
    pub = runner.start(
        f"pub-{path}", "a",
        [sys.executable, __file__, "_pub", "--phases", json.dumps(phases), "--go", go, "--warmup-timeout", "60"],
        runner.graph("a"),
    )  # fmt: skip
    runner.wait_for(sub, "warm", 60)
    time.sleep(1.0)
    open(go, "w").close()
    runner.wait_for(pub, "done", timeout)
    time.sleep(3.0)  # what is still under way arrives
    open(stop, "w").close()
    runner.wait_for(sub, "saved", 30)
    with open(out, encoding="utf-8") as handle:
        return json.load(handle), runner.text(pub)


FETCH = "import sys, urllib.request; sys.stdout.write(urllib.request.urlopen(sys.argv[1], timeout=5).read().decode())"


def scrape(lab, role: str) -> dict[str, float]:
    """The bridge's counters in a namespace (summed over labels), from its /metrics."""
    done = subprocess.run(
        ["ip", "netns", "exec", lab.namespaces[role], sys.executable, "-c", FETCH, f"http://{lab.addresses[role]}:9102/metrics"],
        capture_output=True, text=True, timeout=30,
    )  # fmt: skip
    totals: dict[str, float] = {}
    for line in done.stdout.splitlines():
        if line.startswith("kuberos_bridge_") and "_total" in line:
            name, value = line.split("{")[0].split(" ")[0], float(line.rsplit(" ", 1)[1])
            totals[name] = totals.get(name, 0) + value
    return totals


def percentile(values: list[float], q: float) -> float:
    ordered = sorted(values)
    return ordered[min(len(ordered) - 1, max(0, round(q / 100 * (len(ordered) - 1))))]


def summarize(phases: list[dict], samples: list[list], published_log: str) -> dict[str, dict]:
    results = {}
    published = {}
    for line in published_log.splitlines():
        if line.startswith("phase "):
            _, name, _, count = line.split()
            published[name] = int(count)
    for phase, got in zip(phases, samples, strict=False):
        latencies = [s[0] / 1e6 for s in got]
        entry = {"published": published.get(phase["name"], 0), "received": len(got)}
        if latencies:
            entry.update(p50_ms=percentile(latencies, 50), p99_ms=percentile(latencies, 99), mean_ms=statistics.fmean(latencies))
        if phase["kind"] != "latency" and len(got) > 1:
            span = (got[-1][2] - got[0][2]) / 1e9
            entry["msgs_per_s"] = (len(got) - 1) / span if span > 0 else 0.0
            entry["mb_per_s"] = entry["msgs_per_s"] * phase["size"] / 1e6
        results[phase["name"]] = entry
    return results


def machine() -> dict[str, str]:
    model = "unknown"
    with open("/proc/cpuinfo", encoding="utf-8") as handle:
        for line in handle:
            if line.startswith("model name"):
                model = line.split(":", 1)[1].strip()
                break
    with open("/proc/meminfo", encoding="utf-8") as handle:
        memory = handle.readline().split()[1]
    return {
        "cpus": str(os.cpu_count()), "cpu": model, "memory_gib": f"{int(memory) / 2**20:.0f}",
        "python": platform.python_version(), "kernel": platform.release(),
    }  # fmt: skip


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    sub = parser.add_subparsers(dest="mode")
    pub = sub.add_parser("_pub")
    pub.add_argument("--phases", required=True)
    pub.add_argument("--go", required=True)
    pub.add_argument("--warmup-timeout", type=float, default=60)
    subscriber = sub.add_parser("_sub")
    subscriber.add_argument("--phases", required=True)
    subscriber.add_argument("--out", required=True)
    subscriber.add_argument("--timeout", type=float, default=300)
    subscriber.add_argument("--stop", required=True)
    parser.add_argument("--quick", action="store_true", help="fewer messages (a smoke run, not for RESULTS.md)")
    parser.add_argument("--append", help="append the results section to this Markdown file (bench/RESULTS.md)")
    parser.add_argument("--json", help="write the raw figures to this file")
    args = parser.parse_args()
    if args.mode == "_pub":
        publisher_main(args)
        return 0
    if args.mode == "_sub":
        subscriber_main(args)
        return 0

    if os.geteuid() != 0 or not shutil.which("ip"):
        print("bench_bridge: needs root and `ip netns`", file=sys.stderr)
        return 2
    scale = 0.2 if args.quick else 1.0
    only = os.environ.get("KUBEROS_BENCH_ONLY")
    phases = [
        {"name": "latency-1KB", "kind": "latency", "size": 1024, "rate": 200, "count": int(2000 * scale)},
        {"name": "latency-1MB", "kind": "latency", "size": 1 << 20, "rate": 10, "count": int(100 * scale)},
        {"name": "rate-1KB-5000/s", "kind": "rate", "size": 1024, "rate": 5000, "seconds": 5 * scale, "count": 200_000},
        {"name": "rate-1KB-10000/s", "kind": "rate", "size": 1024, "rate": 10000, "seconds": 5 * scale, "count": 200_000},
        # 1 MB before the 1 KB flood: after the 1 KB overload the bridge delivers badly for a while (bench/RESULTS.md)
        {"name": "flood-1MB", "kind": "flood", "size": 1 << 20, "seconds": 5 * scale, "count": 500, "pause": 4.0},
        {"name": "flood-1KB", "kind": "flood", "size": 1024, "seconds": 5 * scale, "count": 200_000},
    ]
    if only:
        phases = [p for p in phases if p["name"] in only.split(",")]
    sys.path[:0] = [os.path.join(ROOT, "tests", "integration"), os.path.join(ROOT, "tests"), os.path.join(ROOT, ".collections")]
    from test_discovery_netns import Lab

    from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_bridge import generate_certificates

    load_before = os.getloadavg()
    started = datetime.datetime.now(datetime.UTC)
    lab = Lab()
    directory = tempfile.mkdtemp(prefix="kuberos-bench-bridge-")
    runner = None
    results = {}
    try:
        lab.create_bridge()
        lab.add("a")
        lab.add("b")
        runner = Runner(lab, directory)
        for role in ("a", "b"):
            log = runner.start(f"discovery-{role}", role, ["fast-discovery-server", "-i", "0", "-l", "0.0.0.0", "-p", "11811"])
            runner.wait_for(log, "Server ID:", 30)
        certs = generate_certificates(os.path.join(directory, "certs"), "bench.kuberos")
        topics = os.path.join(directory, "topics.yml")
        with open(topics, "w", encoding="utf-8") as handle:
            handle.write(f"topics:\n- {{name: {TOPIC}, type: {TYPE}, direction: to_client, depth: {DEPTH}}}\n")
        timeout = sum(p.get("seconds", p.get("count", 0) / p.get("rate", 1)) + 10 for p in phases) + 60
        results["direct"] = summarize(phases, *run_path(runner, "direct", phases, timeout))
        server = runner.start(
            "bridge-server", "a",
            [sys.executable, "-m", BRIDGE, "server", "--listen", f"{lab.addresses['a']}:50051", "--cert", certs["server_cert"],
             "--key", certs["server_key"], "--ca", certs["ca_cert"], "--topics", topics, "--metrics-port", "9102"],
            runner.graph("a"),
        )  # fmt: skip
        runner.wait_for(server, "server listening", 60)
        client = runner.start(
            "bridge-client", "b",
            [sys.executable, "-m", BRIDGE, "client", "--connect", f"{lab.addresses['a']}:50051", "--server-name",
             "bench.kuberos", "--cert", certs["client_cert"], "--key", certs["client_key"], "--ca", certs["ca_cert"],
             "--topics", topics, "--metrics-port", "9102"],
            runner.graph("b"),
        )  # fmt: skip
        runner.wait_for(client, "connected to server", 60)
        results["bridge"] = summarize(phases, *run_path(runner, "bridge", phases, timeout))
        results["bridge_metrics"] = {role: scrape(lab, role) for role in ("a", "b")}
        runner.stop("bridge-client")
        runner.stop("bridge-server")
        stopped = [line for line in runner.text(client).splitlines() + runner.text(server).splitlines() if "stopped:" in line]
        results["bridge_logs"] = stopped
    finally:
        if runner is not None:
            runner.close()
        lab.close()
    load_after = os.getloadavg()
    report = render(results, phases, started, load_before, load_after, args)
    print(report)
    if args.json:
        with open(args.json, "w", encoding="utf-8") as handle:
            json.dump({"results": results, "machine": machine(), "phases": phases}, handle, indent=2)
    if args.append:
        with open(args.append, "a", encoding="utf-8") as handle:
            handle.write("\n" + report)
    if not os.environ.get("KUBEROS_BENCH_KEEP"):
        shutil.rmtree(directory, ignore_errors=True)
    return 0


def render(results, phases, started, load_before, load_after, args) -> str:
    m = machine()
    command = ".venv/bin/python bench/bench_bridge.py" + (" --quick" if args.quick else "")
    lines = [
        "## Bridge benchmark",
        "",
        f"Date: {started:%a %b %d %H:%M UTC %Y}. Machine: {m['cpus']} CPUs ({m['cpu']}), {m['memory_gib']} GiB, "
        f"Python {m['python']}, Linux {m['kernel']}. Load average (1/5/15 min) before: "
        f"{'/'.join(f'{x:.2f}' for x in load_before)}, after: {'/'.join(f'{x:.2f}' for x in load_after)}.",
        f"Command: `{command}`",
        "",
        "| phase | path | published | received | p50 ms | p99 ms | msgs/s | MB/s |",
        "|---|---|---:|---:|---:|---:|---:|---:|",
    ]
    for phase in phases:
        for path in ("direct", "bridge"):
            r = results.get(path, {}).get(phase["name"], {})
            cells = [
                phase["name"], path, str(r.get("published", "-")), str(r.get("received", "-")),
                f"{r['p50_ms']:.3f}" if "p50_ms" in r else "-", f"{r['p99_ms']:.3f}" if "p99_ms" in r else "-",
                f"{r['msgs_per_s']:,.0f}" if "msgs_per_s" in r else "-", f"{r['mb_per_s']:.1f}" if "mb_per_s" in r else "-",
            ]  # fmt: skip
            lines.append("| " + " | ".join(cells) + " |")
    direct, bridge = results.get("direct", {}), results.get("bridge", {})
    added = bridge.get("latency-1KB", {}).get("p50_ms", float("nan")) - direct.get("latency-1KB", {}).get("p50_ms", float("nan"))
    carried = {name: r for name, r in bridge.items() if name.startswith(("rate-1KB", "flood-1KB")) and r.get("msgs_per_s")}
    best_name = max(carried, key=lambda name: carried[name]["msgs_per_s"], default="")
    best = carried.get(best_name, {})
    rate = best.get("msgs_per_s", 0.0)
    lost = 1 - best.get("received", 0) / max(1, best.get("published", 1))
    offered = bridge.get("rate-1KB-5000/s", {})
    offered_lost = 1 - offered.get("received", 0) / max(1, offered.get("published", 1))
    lines += [
        "",
        f"- Added p50 latency for 1 KB (bridge - direct): {added:.3f} ms (target: under 1 ms): "
        f"{'met' if added < 1 else 'missed'}.",
        f"- 1 KB through the bridge on one connection: at most {rate:,.0f} msgs/s arrived ({best_name}, {lost:.1%} of the "
        f"published lost) (target: at least 5,000): {'met' if rate >= 5000 else 'missed'}. At 5,000/s offered, "
        f"{offered.get('msgs_per_s', 0):,.0f} msgs/s arrived, {offered_lost:.1%} lost.",
        *[
            f"- bridge {'server' if role == 'a' else 'client'} counters: "
            + ", ".join(f"{name.removeprefix('kuberos_bridge_')} {value:,.0f}" for name, value in sorted(totals.items()))
            for role, totals in results.get("bridge_metrics", {}).items()
        ],
        "",
    ]
    return "\n".join(lines)


if __name__ == "__main__":
    sys.exit(main())
