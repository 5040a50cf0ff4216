"""ROS 2 from PyPI wheels (requirements-ros.txt): the environment its programs need, and whether they run.

No Ansible imports: the network-namespace tests, the bridge benchmark and the simulator (sim/kuberos_sim)
all start rclpy and fast-discovery-server processes with this environment.
"""

from __future__ import annotations

import functools
import glob
import os
import subprocess
import sys
import tempfile

# Each process gets a /dev/shm of its own: Fast DDS would otherwise carry data through shared memory between
# the namespaces, which pods on different nodes cannot. `ip netns exec` already runs the command in a mount
# namespace of its own (slave to the host's), so this mount stays private to the process.
# Use as `sh -c PRIVATE_SHM sh <command...>`.
PRIVATE_SHM = 'mount -t tmpfs -o size=64m,mode=1777 kuberos-shm /dev/shm && exec "$@"'


def ros_environment(prefix: str = sys.prefix, log_dir: str | None = None) -> dict[str, str]:
    """The environment that rclpy and fast-discovery-server need when installed from requirements-ros.txt.

    - LD_LIBRARY_PATH: `<prefix>/lib` (librcl, libfastrtps, libfastcdr, the message type support libraries)
      and every `site-packages/ros_*.libs` (the wheels' vendored libraries, e.g. ros_fastrtps.libs with
      tinyxml2 and OpenSSL). Both the loader and rmw's dlopen() of librmw_fastrtps_cpp.so rely on it.
    - _ROS_WHEELS_BOOTSTRAP_COMPLETE=1: the ros-wheels-bootstrapper .pth otherwise re-executes every Python
      process of the venv once, only to set the same LD_LIBRARY_PATH.
    - ROS_LOG_DIR: rclpy.init() fails ("Failed to get logging directory") without it or HOME.
    - PATH starts with `<prefix>/bin`, so the rendered command's `fast-discovery-server` is the wheel's program.
    AMENT_PREFIX_PATH is not needed. A rendered container's environment goes on top of this.
    """
    site_packages = os.path.join(prefix, "lib", f"python{sys.version_info.major}.{sys.version_info.minor}", "site-packages")
    libraries = [os.path.join(prefix, "lib"), *sorted(glob.glob(os.path.join(site_packages, "ros_*.libs")))]
    env = {
        "PATH": os.pathsep.join(
            [os.path.join(prefix, "bin"), "/usr/local/sbin", "/usr/local/bin", "/usr/sbin", "/usr/bin", "/sbin", "/bin"]
        ),
        "LD_LIBRARY_PATH": os.pathsep.join(libraries),
        "_ROS_WHEELS_BOOTSTRAP_COMPLETE": "1",
        "PYTHONUNBUFFERED": "1",
        "LANG": "C.UTF-8",
    }
    if log_dir:
        env["ROS_LOG_DIR"] = log_dir
    return env


@functools.cache
def ros_problem(prefix: str = sys.prefix) -> str | None:
    """Why rclpy with Fast DDS or the discovery server program cannot run from this venv (None if they can)."""
    program = os.path.join(prefix, "bin", "fast-discovery-server")
    if not os.access(program, os.X_OK):
        return f"{program} is missing"
    check = "import rclpy, std_msgs.msg; rclpy.init(); rclpy.create_node('kuberos_check'); rclpy.shutdown()"
    with tempfile.TemporaryDirectory(prefix="kuberos-ros-check-") as log_dir:
        env = ros_environment(prefix, log_dir=log_dir)
        python = os.path.join(prefix, "bin", "python3")
        for command in ([python if os.access(python, os.X_OK) else sys.executable, "-c", check], [program, "-h"]):
            try:
                done = subprocess.run(command, env=env, capture_output=True, text=True, timeout=60, check=False)
            except (OSError, subprocess.TimeoutExpired) as error:
                return f"{command[0]}: {error}"
            if done.returncode != 0:
                return f"{' '.join(command)} exited {done.returncode}:\n{done.stdout[-2000:]}{done.stderr[-2000:]}"
    return None
