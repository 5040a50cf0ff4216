#!/usr/bin/env python3
"""Refusal benchmark: how long and how much memory it takes to refuse a hostile RosDeployment file.

Four files, each written to a temporary directory and refused:

(a) ``1mib``: a spec just under the 1 MiB limit and under every count limit (100 modules, each with a ROS
    parameter list of 20-character strings: about 47,000 YAML nodes), whose very last value is a YAML
    timestamp ROS 2 cannot read: every byte is read, parsed, constructed and validated before the refusal;
(b) ``10000-documents``: 10,000 small RosDeployment documents in one file (under 1 MiB), refused at the
    201st document (the limit is 200);
(c) ``alias-bomb``: a "billion laughs" YAML alias structure of 9^10 nodes, refused when the walk of its
    node graph passes 100,000 nodes, before anything is constructed;
(d) ``multibyte-over-limit``: 1 MiB + 1 byte of two-byte UTF-8 text (é), refused as too large from its byte
    count, before decoding.

Each file is refused two ways, each in a fresh process, ``--repeat`` times:

- **filter**: a fresh Python child imports the ``rosdeployment_targets`` filter (which the deploy's
  validation uses: ``spec.load_rosdeployment_file``) and calls it on the file. The child times the call
  (``time.perf_counter`` around it) and the parent records the child's wall time and its peak RSS
  (``os.wait4``'s ``ru_maxrss``).
- **playbook**: ``ansible-playbook playbooks/deploy.yml -e rosdeployment_file=<file> -e kuberos_apply=false
  -e kuberos_render_dir=<empty dir>``: wall time from start to exit, and ``ru_maxrss`` of ``os.wait4``
  (the largest process of the tree: Linux reports the maximum over the process and its waited-for
  children). Each run must exit non-zero, print the expected reason on a located line, show no Python
  traceback, and leave the render directory empty. The floor is the same command stopped by the playbook's
  first task (no ``rosdeployment_file``): what Ansible itself takes to start, fail and exit.

    .venv/bin/python bench/bench_refusal.py                      # 3 repeats, results/refusal.json
    .venv/bin/python bench/bench_refusal.py --repeat 1 --json /tmp/refusal.json

The result is printed as Markdown, ready to paste into bench/RESULTS.md.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
VENV_BIN = REPO / ".venv" / "bin"
MAX_BYTES = 1024 * 1024
TARGET_SECONDS = 2.0
TARGET_MB = 200.0

MODULE = """- name: m{index}
  image: registry.example/planner:1.0
  launch: ros2 run planner node
  rosParameters:
    frames: [{frames}]
"""
HEAD = "metadata:\n  name: big\n  targetFleet: test-fleet\nrosModules:\n"
DOCUMENT = "---\nmetadata: {{name: d{index}, targetFleet: test-fleet}}\nrosModules: [{{name: m, image: r/i:1, launch: x}}]\n"
MODULES = 100


def one_mib_spec() -> str:
    """100 modules with a parameter list each, filled to just under 1 MiB; the last value is a date."""
    frame = "frame_{:014d}"  # 20 characters
    per_module = (MAX_BYTES - 200 * MODULES) // (MODULES * (len(frame.format(0)) + 2))
    modules = []
    for index in range(MODULES):
        frames = [frame.format(index * per_module + n) for n in range(per_module)]
        if index == MODULES - 1:
            frames[-1] = "2024-05-01"
        modules.append(MODULE.format(index=index, frames=", ".join(frames)))
    text = HEAD + "".join(modules)
    assert len(text.encode()) <= MAX_BYTES, len(text.encode())
    return text


def many_documents(count: int = 10_000) -> str:
    return "".join(DOCUMENT.format(index=index) for index in range(count))


def alias_bomb(levels: int = 9, width: int = 9) -> str:
    text = 'lol0: &lol0 ["lol", "lol", "lol", "lol", "lol", "lol", "lol", "lol", "lol"]\n'
    for level in range(1, levels + 1):
        text += f"lol{level}: &lol{level} [{', '.join([f'*lol{level - 1}'] * width)}]\n"
    return text


def multibyte_over_limit() -> bytes:
    body = ("# " + "é" * (MAX_BYTES // 2)).encode("utf-8")
    return body[: MAX_BYTES + 1] if len(body) > MAX_BYTES else body + b"x" * (MAX_BYTES + 1 - len(body))


# name -> (content, the reason the refusal must give)
CASES = {
    "1mib": (one_mib_spec, "rosModules[99].rosParameters.frames[466]: is a YAML timestamp (2024-05-01)"),
    "10000-documents": (many_documents, "file too large: more than 200 documents"),
    "alias-bomb": (alias_bomb, "document too large: more than 100000 YAML nodes (aliases included)"),
    "multibyte-over-limit": (multibyte_over_limit, "file is larger than 1048576 bytes"),
}

CHILD = r"""
import json, sys, time
started = time.perf_counter()
from ansible.errors import AnsibleFilterError
from ansible_collections.kuberos.platform.plugins.filter.rosdeployment_targets import rosdeployment_targets
imported = time.perf_counter()
try:
    rosdeployment_targets(sys.argv[1])
    message = ""
except AnsibleFilterError as exc:
    message = str(exc)
done = time.perf_counter()
print(json.dumps({"import_s": imported - started, "call_s": done - imported, "message": message}))
"""


def run_measured(command: list[str], env: dict | None = None, cwd: Path = REPO) -> tuple[float, float, int, str]:
    """Wall seconds, peak RSS in MB (os.wait4), exit status and output of one process."""
    with tempfile.TemporaryFile() as out:
        started = time.perf_counter()
        process = subprocess.Popen(command, cwd=cwd, env=env, stdout=out, stderr=subprocess.STDOUT)
        _pid, status, usage = os.wait4(process.pid, 0)
        wall = time.perf_counter() - started
        process.returncode = os.waitstatus_to_exitcode(status)
        out.seek(0)
        text = out.read().decode("utf-8", "replace")
    return wall, usage.ru_maxrss / 1024, process.returncode, text


def filter_run(path: Path, reason: str) -> dict:
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(REPO / ".collections"), os.environ.get("PYTHONPATH", "")])}
    wall, rss, code, text = run_measured([str(VENV_BIN / "python"), "-c", CHILD, str(path)], env)
    result = json.loads(text.strip().splitlines()[-1])
    assert code == 0 and reason in result["message"], text[-2000:]
    assert "Traceback" not in result["message"]
    return {"wall_s": wall, "refusal_s": result["call_s"], "import_s": result["import_s"], "peak_rss_mb": rss}


def playbook_run(path: Path, reason: str, workdir: Path) -> dict:
    render = workdir / "render"
    render.mkdir(exist_ok=True)
    env = {**os.environ, "ANSIBLE_CONFIG": str(REPO / "ansible.cfg"), "ANSIBLE_NOCOLOR": "1"}
    command = [
        str(VENV_BIN / "ansible-playbook"), "playbooks/deploy.yml", "-i", "inventories/local",
        "-e", f"rosdeployment_file={path}", "-e", "kuberos_apply=false", "-e", f"kuberos_render_dir={render}",
    ]  # fmt: skip
    wall, rss, code, text = run_measured(command, env)
    assert code != 0, text[-3000:]
    assert any(str(path) in line and reason in line for line in text.splitlines()), text[-3000:]
    assert "Traceback" not in text, text[-3000:]
    assert not os.listdir(render), os.listdir(render)
    return {"wall_s": wall, "peak_rss_mb": rss, "exit_code": code}


def playbook_floor(workdir: Path) -> dict:
    """The same playbook stopped by its very first task (no rosdeployment_file): Ansible's own start-up and teardown."""
    env = {**os.environ, "ANSIBLE_CONFIG": str(REPO / "ansible.cfg"), "ANSIBLE_NOCOLOR": "1"}
    command = [
        str(VENV_BIN / "ansible-playbook"), "playbooks/deploy.yml", "-i", "inventories/local",
        "-e", "rosdeployment_file=", "-e", "kuberos_apply=false", "-e", f"kuberos_render_dir={workdir / 'render'}",
    ]  # fmt: skip
    wall, rss, code, text = run_measured(command, env)
    assert code != 0 and "Set rosdeployment_file" in text, text[-2000:]
    return {"wall_s": wall, "peak_rss_mb": rss}


def summary(runs: list[dict], key: str) -> dict:
    values = [run[key] for run in runs]
    return {"median": round(statistics.median(values), 3), "max": round(max(values), 3)}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--repeat", type=int, default=3)
    parser.add_argument("--json", default=str(REPO / "bench" / "results" / "refusal.json"))
    parser.add_argument("--skip-playbook", action="store_true", help="only the filter in a fresh Python child")
    args = parser.parse_args()

    results = {}
    load_before = Path("/proc/loadavg").read_text().split()[:3]
    with tempfile.TemporaryDirectory(prefix="kuberos-bench-refusal-") as tmp:
        workdir = Path(tmp)
        for name, (make, reason) in CASES.items():
            content = make()
            data = content if isinstance(content, bytes) else content.encode("utf-8")
            path = workdir / f"{name}.yml"
            path.write_bytes(data)
            filters = [filter_run(path, reason) for _ in range(args.repeat)]
            playbooks = [] if args.skip_playbook else [playbook_run(path, reason, workdir) for _ in range(args.repeat)]
            results[name] = {
                "bytes": len(data),
                "reason": reason,
                "filter": {
                    "refusal_s": summary(filters, "refusal_s"),
                    "process_wall_s": summary(filters, "wall_s"),
                    "peak_rss_mb": summary(filters, "peak_rss_mb"),
                    "runs": filters,
                },
                "playbook": {
                    "wall_s": summary(playbooks, "wall_s"),
                    "peak_rss_mb": summary(playbooks, "peak_rss_mb"),
                    "runs": playbooks,
                }
                if playbooks
                else None,
            }
            print(
                f"{name}: {json.dumps({k: v for k, v in results[name].items() if k != 'reason'}, default=str)[:300]}",
                file=sys.stderr,
            )

    floor = [] if args.skip_playbook else [playbook_floor(Path(tempfile.mkdtemp())) for _ in range(args.repeat)]
    report = {
        "date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()),
        "machine": {"nproc": os.cpu_count(), "python": platform.python_version(), "kernel": platform.release()},
        "commit": subprocess.run(
            ["git", "rev-parse", "--short", "HEAD"], cwd=REPO, capture_output=True, text=True
        ).stdout.strip(),
        "load_before": load_before,
        "load_after": Path("/proc/loadavg").read_text().split()[:3],
        "repeat": args.repeat,
        "target": {"seconds": TARGET_SECONDS, "peak_rss_mb": TARGET_MB},
        "cases": results,
        "playbook_floor": {"wall_s": summary(floor, "wall_s"), "peak_rss_mb": summary(floor, "peak_rss_mb")} if floor else None,
    }
    Path(args.json).parent.mkdir(parents=True, exist_ok=True)
    Path(args.json).write_text(json.dumps(report, indent=2) + "\n", encoding="utf-8")
    print_markdown(report)
    return 0


def print_markdown(report: dict) -> None:
    print(
        f"Date {report['date']}, commit {report['commit']}, {report['repeat']} runs per case, "
        f"load {' '.join(report['load_before'])} before, {' '.join(report['load_after'])} after.\n"
    )
    print("| file | bytes | filter: refusal s (median / max) | filter: process s | filter: peak RSS MB | "
          "playbook: wall s (median / max) | playbook: peak RSS MB |")  # fmt: skip
    print("|---|---:|---:|---:|---:|---:|---:|")
    floor = report["playbook_floor"]
    if floor:
        print(
            f"| (floor: deploy.yml stopped by its first task) | | | | | {floor['wall_s']['median']:.2f} / "
            f"{floor['wall_s']['max']:.2f} | {floor['peak_rss_mb']['max']:.0f} |"
        )
    for name, case in report["cases"].items():
        f, p = case["filter"], case["playbook"]
        playbook = f"{p['wall_s']['median']:.2f} / {p['wall_s']['max']:.2f} | {p['peak_rss_mb']['max']:.0f}" if p else "- | -"
        print(
            f"| {name} | {case['bytes']} | {f['refusal_s']['median']:.3f} / {f['refusal_s']['max']:.3f} | "
            f"{f['process_wall_s']['median']:.2f} | {f['peak_rss_mb']['max']:.0f} | {playbook} |"
        )


if __name__ == "__main__":
    sys.exit(main())
