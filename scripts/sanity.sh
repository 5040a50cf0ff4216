#!/usr/bin/env bash
# ansible-test sanity, the checks every Galaxy collection is held to, on the collection as it ships: the tarball that
# `ansible-galaxy collection build` makes (galaxy.yml's build_ignore leaves out sim/, bench/, the test suites...),
# unpacked under a temporary .../ansible_collections/kuberos/platform, the layout ansible-test requires (the checkout's
# .collections link resolves to the checkout itself, which ansible-test refuses).
#
# ansible-test installs each test's pinned tools (pylint, pycodestyle, yamllint, voluptuous...) from PyPI into
# virtualenvs of its own under $HOME/.ansible/test/venv; HOME is ${KUBEROS_CACHE_DIR:-~/.cache/kuberos}/ansible-test
# here, kept between runs (scripts/setup.sh fills it with --prime-venvs). It puts pip into each with a get-pip.py from
# its own file server, which this machine cannot reach: scripts/ansible_test_get_pip.py stands in.
#
# Usage: scripts/sanity.sh [ansible-test sanity options], e.g. --test pylint, or --prime-venvs to install only.
set -euo pipefail
cd "$(dirname "$0")/.."
checkout=$PWD

if [ ! -x .venv/bin/ansible-test ]; then
  echo "sanity: .venv/bin/ansible-test is missing: run 'make setup' first" >&2
  exit 2
fi

home="${KUBEROS_CACHE_DIR:-$HOME/.cache/kuberos}/ansible-test"
pip_version=$(.venv/bin/python -c 'import types
from ansible_test._internal.python_requirements import get_venv_packages
print(get_venv_packages(types.SimpleNamespace(version="3.11"))["pip"])')
mkdir -p "$home/.ansible/test/cache"
cp scripts/ansible_test_get_pip.py "$home/.ansible/test/cache/get_pip_${pip_version//./_}.py"

work=$(mktemp -d)
trap 'rm -rf "$work"' EXIT
.venv/bin/ansible-galaxy collection build --output-path "$work" >/dev/null
collection="$work/ansible_collections/kuberos/platform"
mkdir -p "$collection"
tar -xzf "$work"/kuberos-platform-*.tar.gz -C "$collection"

# Not run: shellcheck when the program is missing (setup.sh installs it with apt as root).
skip=()
command -v shellcheck >/dev/null 2>&1 || skip+=(--skip-test shellcheck)

cd "$collection"
# Python 3.11 only: the version of .venv, the one Python this project installs and runs its modules with.
env -u ANSIBLE_CONFIG -u ANSIBLE_COLLECTIONS_PATH HOME="$home" PATH="$checkout/.venv/bin:$PATH" \
  ansible-test sanity --python 3.11 --color no "${skip[@]}" "$@"
