# Copyright: KubeROS contributors
# GNU General Public License v3.0+ (see https://www.gnu.org/licenses/gpl-3.0.txt)
"""What the module attributes mean; each module says its support (as community.general's attributes fragment)."""

from __future__ import annotations


class ModuleDocFragment:
    # Every module: check mode and diff mode.
    DOCUMENTATION = r"""
options: {}
attributes:
  check_mode:
    description: Can run in check mode and report what it would change without changing it.
  diff_mode:
    description: Returns what it changed (or would change in check mode) as a diff when diff mode is on.
"""

    # A module whose work an action plugin of the same name does on the controller.
    ACTION = r"""
options: {}
attributes:
  action:
    description: Has an action plugin of the same name that does the work, or part of it, on the controller.
"""
