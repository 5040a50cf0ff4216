"""``python -m ansible_collections.kuberos.platform.plugins.module_utils.kuberos_controller``: the controller process (cli.py)."""

import sys

from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_controller.cli import main

if __name__ == "__main__":
    sys.exit(main())  # pylint: disable=ansible-bad-function
