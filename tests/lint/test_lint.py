"""Lint as the ecosystem does: ruff, yamllint and ansible-lint (production profile)."""

from __future__ import annotations

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
def test_lint(command):
    result = subprocess.run([venv_tool(command[0]), *command[1:]], cwd=ROOT, capture_output=True, text=True, timeout=600)
    assert result.returncode == 0, result.stdout[-4000:] + result.stderr[-4000:]
