"""Lint as the ecosystem does: ruff, yamllint and ansible-lint (production profile)."""

from __future__ import annotations

import os
import subprocess

import pytest
from helpers import ROOT, venv_tool

pytestmark = pytest.mark.lint


@pytest.mark.parametrize(
    "command",
    [
        ["ruff", "check", "."],
        ["ruff", "format", "--check", "."],
        ["yamllint", "--strict", "."],
        ["ansible-lint", "--offline", "--profile", "production"],
    ],
    ids=["ruff", "ruff-format", "yamllint", "ansible-lint"],
)
def test_lint(command, tmp_path):
    env = dict(os.environ)
    if command[0] == "ansible-lint":
        # A home of its own: molecule installs this collection into ~/.ansible/collections, and ansible-lint would
        # resolve the collection's modules from that (older) copy instead of the checkout.
        env["HOME"] = str(tmp_path)
    result = subprocess.run([venv_tool(command[0]), *command[1:]], cwd=ROOT, capture_output=True, text=True, timeout=600, env=env)
    assert result.returncode == 0, result.stdout[-4000:] + result.stderr[-4000:]
