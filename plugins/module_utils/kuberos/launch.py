"""How a module's launch lines run: one container each, started with a literal argv and no shell.

A launch line becomes an argv by POSIX word splitting and nothing else (``shlex.split`` without comments):
quotes and backslashes group and escape words, and that is all. ``$``, backquotes, ``*``, ``;``, ``&``, ``&&``,
``|``, ``>``, ``#`` and every other shell character reach the program unchanged, as parts of its arguments; no
command substitution, variable expansion, globbing, pipeline, redirection or comment happens. The one
substitution left is Kubernetes' own: the kubelet replaces ``$(NAME)`` in ``args`` when ``NAME`` is one of the
container's environment variables (``$(KUBEROS_ROBOT_NAME)``), and ``$$`` stands for a literal ``$``.

A module with several launch lines gets one container per line in its pod. They share the module's image,
environment, volumes and node; each restarts on its own. The module's requests (the amounts the placement
counted) are divided among them so that the pod asks for exactly what was placed; see ``split_amount``.

Pure: no Ansible, no Kubernetes.
"""

from __future__ import annotations

import shlex


def launch_argv(line: str) -> list[str]:
    """The argv of one launch line: ``"ros2 run pkg node --ros-args -p 'name:=a b'"`` ->
    ``['ros2', 'run', 'pkg', 'node', '--ros-args', '-p', 'name:=a b']``. Raises ``ValueError`` for an unclosed
    quote or an empty line (the spec's validation reports those with file and line)."""
    argv = shlex.split(line, comments=False, posix=True)
    if not argv:
        raise ValueError("empty command")
    return argv


def container_name(module: str, number: int) -> str:
    """The container of launch line ``number``: the module's name for the first line (so that a one-line module's
    pod looks as it always did), ``<module>-<number>`` for the others (``launch[1]`` runs in ``<module>-1``)."""
    return module if number == 0 else f"{module}-{number}"


def split_amount(total: int, parts: int) -> list[int]:
    """``total`` divided into ``parts`` whole shares that add up to ``total`` exactly, the larger ones first:
    ``split_amount(1000, 3) == [334, 333, 333]``."""
    if parts < 1:
        raise ValueError("parts must be at least 1")
    share, rest = divmod(total, parts)
    return [share + (1 if index < rest else 0) for index in range(parts)]
