"""ansible-test sanity, the checks every Galaxy collection is held to, on the collection as it ships (scripts/sanity.sh:
the built tarball, Python 3.11, the tools from PyPI; tests/sanity/ignore-2.19.txt justifies each exception)."""

from __future__ import annotations

import os
import subprocess

import pytest
from helpers import ROOT

pytestmark = pytest.mark.lint


def test_ansible_test_sanity():
    # scripts/sanity.sh gives ansible-test a home of its own (its virtualenvs, kept between runs), so that nothing in
    # ~/.ansible (molecule's copy of this collection) is read either.
    result = subprocess.run(
        [os.path.join(ROOT, "scripts", "sanity.sh")], cwd=ROOT, capture_output=True, text=True, timeout=1500, check=False
    )
    assert result.returncode == 0, result.stdout[-6000:] + result.stderr[-6000:]
