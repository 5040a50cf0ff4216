"""Long steps are never silent: the control plane build, set-up's installs and the image builds print a line at
least every KUBEROS_PROGRESS_INTERVAL seconds (30) while they run, and their time when they end.

The helpers run for real with a 1-second (shell) or 0.2-second (Python) interval on commands that sleep; the
static checks make every long command of build-binaries.sh, build-cilium.sh and setup.sh, and the role's build task, use them.
"""

from __future__ import annotations

import os
import re
import subprocess
import time

import pytest
import yaml
from helpers import ROOT

from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_lab import local_images

PROGRESS = os.path.join(ROOT, "roles", "local_cluster", "files", "progress.sh")
BUILD = os.path.join(ROOT, "roles", "local_cluster", "files", "build-binaries.sh")
BUILD_CILIUM = os.path.join(ROOT, "roles", "local_cluster", "files", "build-cilium.sh")
SETUP = os.path.join(ROOT, "scripts", "setup.sh")
STILL = re.compile(r"^\[\d\d:\d\d:\d\d\]   still sleeping a while \.\.\. 0m0(\d)s elapsed \(about 3 s\)$")


def _with_progress(command: str, interval: str = "1") -> tuple[subprocess.CompletedProcess, float]:
    started = time.monotonic()
    done = subprocess.run(
        ["bash", "-c", f'source "{PROGRESS}"; {command}'],
        env={**os.environ, "KUBEROS_PROGRESS_INTERVAL": interval},
        capture_output=True, text=True, timeout=30, check=False,
    )  # fmt: skip
    return done, time.monotonic() - started


def test_a_long_step_prints_a_line_every_interval_and_its_time_when_done():
    done, seconds = _with_progress('with_progress --about "about 3 s" "sleeping a while" -- sleep 3.5; echo "status $?"')
    lines = done.stdout.splitlines()
    ticks = [int(match.group(1)) for match in map(STILL.match, lines) if match]
    assert len(ticks) >= 2 and ticks == sorted(ticks) and ticks[0] >= 1, done.stdout
    assert re.fullmatch(r"\[\d\d:\d\d:\d\d\] done sleeping a while in 0m0[34]s", lines[-2]), done.stdout
    assert lines[-1] == "status 0"
    assert seconds < 6, "the ticker's sleep must not hold the output open after the step ends"


def test_a_failed_step_says_so_and_keeps_its_status():
    done, _seconds = _with_progress("with_progress 'failing soon' -- bash -c 'sleep 1.5; exit 3'; echo \"status $?\"")
    lines = done.stdout.splitlines()
    assert any("still failing soon ... 0m01s elapsed" in line for line in lines), done.stdout
    assert re.fullmatch(r"\[\d\d:\d\d:\d\d\] failed failing soon after 0m0[12]s \(exit 3\)", lines[-2]), done.stdout
    assert lines[-1] == "status 3"


def test_a_short_step_prints_only_its_time():
    done, _seconds = _with_progress("with_progress 'being quick' -- true", interval="30")
    assert re.fullmatch(r"\[\d\d:\d\d:\d\d\] done being quick in 0m00s\n", done.stdout), done.stdout


def test_the_image_builds_progress_lines(monkeypatch):
    monkeypatch.setenv("KUBEROS_PROGRESS_INTERVAL", "0.2")
    lines: list[str] = []
    with local_images._progress(lines.append, "packing the rootfs"):
        time.sleep(0.9)
    assert len(lines) >= 3, lines
    assert all(line == "local images:   still packing the rootfs ... 0m00s elapsed" for line in lines), lines
    count = len(lines)
    time.sleep(0.5)
    assert len(lines) == count, "the ticker stops with the step"


def _logical_lines(path: str) -> list[str]:
    """The script's commands with their continuation lines joined."""
    with open(path, encoding="utf-8") as handle:
        return re.sub(r"\\\n\s*", " ", handle.read()).splitlines()


# The commands that can take minutes: compiling or downloading Go modules, making a venv, installing wheels or packages.
LONG = {
    BUILD: re.compile(r'"\$GO" (build|install|mod tidy|list -mod=mod -deps)\b'),
    BUILD_CILIUM: re.compile(r'"\$GO" (build|install|mod tidy|list -mod=mod)\b'),
    SETUP: re.compile(r"pip install|apt-get install|-m venv"),
}


@pytest.mark.parametrize("script", sorted(LONG), ids=os.path.basename)
def test_every_long_command_runs_with_progress(script):
    long = [line.strip() for line in _logical_lines(script) if LONG[script].search(line)]
    assert long, f"no long commands found in {script}: is the pattern stale?"
    silent = [line for line in long if "with_progress" not in line]
    assert not silent, f"long commands without progress lines in {script}: {silent}"


def test_the_roles_build_shows_progress_in_ansible():
    """Ansible shows a task only when it ends: the build runs in the background and is polled at least every 30 s."""
    with open(os.path.join(ROOT, "roles", "local_cluster", "tasks", "main.yml"), encoding="utf-8") as handle:
        pending = yaml.safe_load(handle)
    builds = []
    while pending:
        task = pending.pop()
        pending.extend(task.get("block", []))
        command = task.get("ansible.builtin.command", {})
        if "build-binaries.sh" in str(command) and "--print-paths" not in str(command):
            builds.append(task)
    assert builds, "the role's build task was not found"
    for task in builds:
        assert task.get("async", 0) > 0 and 0 < task.get("poll", 0) <= 30, task["name"]
