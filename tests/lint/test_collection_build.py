"""The collection tarball holds the collection and nothing of the checkout (galaxy.yml's build_ignore)."""

from __future__ import annotations

import subprocess
import tarfile

import pytest
from helpers import ROOT, venv_tool

pytestmark = pytest.mark.lint

# What ships at the top of the tarball; anything else new at the top must be added here or to build_ignore.
SHIPPED = {
    "FILES.json",
    "MANIFEST.json",
    "README.md",
    "changelogs",
    "docs",
    "examples",
    "inventories",
    "meta",
    "playbooks",
    "plugins",
    "requirements.txt",
    "roles",
    "tests",
}
REQUIRED = [
    "meta/runtime.yml",
    "plugins/modules/rosdeployment_render.py",
    "plugins/filter/place_modules.py",
    "plugins/plugin_utils/filter_errors.py",
    "roles/rosdeployment/tasks/main.yml",
    "playbooks/deploy.yml",
]
LEFT_OUT = [
    ".venv",
    ".collections",
    ".ci",
    ".config",
    ".hypothesis",
    ".pytest_cache",
    ".ruff_cache",
    "sim",
    "bench",
    "rendered",
    "scripts",
    "molecule",
    "Makefile",
    "ansible.cfg",
    "galaxy.yml",
]


@pytest.fixture(scope="module")
def tarball_names(tmp_path_factory) -> list[str]:
    out = tmp_path_factory.mktemp("build")
    result = subprocess.run(
        [venv_tool("ansible-galaxy"), "collection", "build", "--output-path", str(out)],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert result.returncode == 0, result.stdout + result.stderr
    (tarball,) = out.glob("kuberos-platform-*.tar.gz")
    with tarfile.open(tarball) as archive:
        return [name.rstrip("/") for name in archive.getnames()]


def test_the_top_holds_only_the_collection(tarball_names):
    top = {name.split("/", 1)[0] for name in tarball_names}
    assert top == SHIPPED, f"unexpected: {sorted(top - SHIPPED)}, missing: {sorted(SHIPPED - top)}"


@pytest.mark.parametrize("path", REQUIRED)
def test_collection_content_ships(tarball_names, path):
    assert path in tarball_names


@pytest.mark.parametrize("path", LEFT_OUT)
def test_checkout_content_is_left_out(tarball_names, path):
    assert not [name for name in tarball_names if name == path or name.startswith(path + "/")]


def test_tests_ship_only_the_sanity_configuration(tarball_names):
    """The pytest suites need the checkout; ansible-test's ignore file ships so that sanity gives the same result."""
    tests = {name for name in tarball_names if name.startswith("tests/")}
    assert tests and all(name.startswith("tests/sanity") for name in tests), sorted(tests)
    assert not [name for name in tarball_names if "__pycache__" in name or name.endswith(".pyc")]
