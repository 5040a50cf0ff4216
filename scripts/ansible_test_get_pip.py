"""Stands in for the get-pip.py that ansible-test downloads from its own file server to put pip into each of its
sanity test virtualenvs (created without pip). That server is not reachable from here, PyPI is: pip comes from the
interpreter's ensurepip, then pip installs what ansible-test asked for (the pip version it pins) from PyPI.

scripts/sanity.sh copies it to where ansible-test caches the script it downloads,
$HOME/.ansible/test/cache/get_pip_<version>.py, which ansible-test then runs as
``python get_pip.py [pip options] pip==<version> --no-setuptools --no-wheel``.
"""

from __future__ import annotations

import subprocess
import sys

GET_PIP_ONLY = ("--no-setuptools", "--no-wheel")  # get-pip.py's options that pip install does not have


def main(argv: list[str]) -> int:
    subprocess.run([sys.executable, "-m", "ensurepip", "--default-pip"], check=True, stdout=subprocess.DEVNULL)
    subprocess.run([sys.executable, "-m", "pip", "install", "--quiet", *(a for a in argv if a not in GET_PIP_ONLY)], check=True)
    if "--no-setuptools" in argv:  # ensurepip brings setuptools on Python 3.11
        subprocess.run([sys.executable, "-m", "pip", "uninstall", "--quiet", "--yes", "setuptools"], check=True)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
