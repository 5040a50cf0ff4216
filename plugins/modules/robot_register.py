#!/usr/bin/python
# Copyright: KubeROS contributors
# GNU General Public License v3.0+ (see https://www.gnu.org/licenses/gpl-3.0.txt)
"""Register a new robot by SSH: pin its host key, install the cluster's key, write its hardware to the inventory."""

from __future__ import annotations

DOCUMENTATION = r"""
module: robot_register
short_description: Register a new robot by SSH and write its hardware facts to the inventory
version_added: 0.2.0
description:
  - Runs on the machine that holds the inventory. Connects to the robot with the administrator's key only (no
    agent, no other keys), checks its SSH host key against the site's pinned keys in O(known_hosts), installs the
    cluster's public key O(cluster_key) in the login user's C(~/.ssh/authorized_keys) (appended once, mode 0600),
    reads the robot's hardware (C(nproc), C(MemTotal) of C(/proc/meminfo), C(uname -m), GPUs, device nodes) and
    writes C(<inventory_dir>/host_vars/<name>.yml) and C(<inventory_dir>/registered_robots.yml), which makes the
    robot a host of the group C(robots).
  - "Host key pinning: on first contact the presented key is pinned (trust on first use, its SHA256 fingerprint
    reported), unless O(expected_fingerprint) is given, which it must match. A robot whose key differs from the
    pinned one is refused, naming both fingerprints."
  - Nothing is written unless every step succeeded. Each file is replaced atomically (a temporary file and a
    rename), the pin included, and the group membership is written last. Keys of the host_vars file other than
    the ones this module writes are kept.
  - Idempotent; registering again with the same hardware changes nothing. With check mode the robot is contacted
    and read but nothing is written or installed; with diff mode the files that would be written are shown.
options:
  name:
    description: Inventory name of the robot (also its node name and robot name unless the inventory says otherwise).
    type: str
    required: true
  address:
    description: Address (IP or DNS name) at which this machine and the cluster reach the robot by SSH.
    type: str
    required: true
  port:
    description: SSH port of the robot.
    type: int
    default: 22
  user:
    description: Login user on the robot; the cluster's key is installed for this user.
    type: str
    default: root
  fleet:
    description: The fleet the robot belongs to (C(kuberos_fleet)).
    type: str
    required: true
  inventory_dir:
    description: The inventory directory that gets C(host_vars/<name>.yml) and C(registered_robots.yml).
    type: path
    required: true
  known_hosts:
    description:
      - The site's pinned SSH host keys, in OpenSSH known_hosts format. Created on the first registration.
      - Keep it out of the inventory's inventory sources (a file in the inventory directory whose name starts
        with a dot, such as C(<inventory_dir>/.known_hosts), is never read as an inventory).
    type: path
    required: true
  expected_fingerprint:
    description:
      - SHA256 fingerprint the robot's host key must have on first contact (C(SHA256:...), as C(ssh-keygen -lf)
        prints it), read from the robot's console. Empty for trust on first use.
    type: str
    default: ""
  admin_key:
    description: The administrator's private key, already authorized on the robot. The only key tried.
    type: path
    required: true
  admin_key_passphrase:
    description: Passphrase of O(admin_key) when it is encrypted.
    type: str
  cluster_key:
    description: The cluster's public key (a C(.pub) file) to install on the robot.
    type: path
    required: true
  device_globs:
    description:
      - Device nodes to look for and the inventory device name each stands for (C(kuberos_devices)); a name
        appears when any node matches its glob.
    type: dict
    default: {"/dev/video*": camera, "/dev/ttyUSB*": serial, "/dev/ttyACM*": serial}
  extra_devices:
    description: Device names the robot carries that have no device node to find (a network lidar, a gripper).
    type: list
    elements: str
    default: []
  connect_timeout:
    description: Seconds to wait for the TCP connection, the SSH handshake and the authentication each.
    type: float
    default: 10
  command_timeout:
    description: Seconds the commands on the robot may take.
    type: float
    default: 60
requirements:
  - paramiko (on the machine running Ansible)
attributes:
  check_mode:
    support: full
  diff_mode:
    support: full
notes:
  - Errors (unreachable robot, refused key, changed host key, unexpected fingerprint) are one sentence each, and
    leave the inventory and the pins as they were.
extends_documentation_fragment:
  - kuberos.platform.attributes
author:
  - KubeROS contributors (@kuberos)
"""

EXAMPLES = r"""
- name: Register fetch-9
  kuberos.platform.robot_register:
    name: fetch-9
    address: 192.0.2.19
    fleet: test-fleet
    inventory_dir: inventories/site
    known_hosts: inventories/site/.known_hosts
    admin_key: ~/.ssh/id_ed25519
    cluster_key: inventories/site/files/cluster_ed25519.pub

- name: Register tiago-3, whose host key fingerprint was read on its console
  kuberos.platform.robot_register:
    name: tiago-3
    address: tiago-3.site.example
    user: admin
    fleet: warehouse-fleet
    inventory_dir: inventories/site
    known_hosts: inventories/site/.known_hosts
    expected_fingerprint: SHA256:n0l5Q7g6nqhGcS8mYpGcv0t2Vw8cQfOe0n0m4k8ZkxY
    admin_key: ~/.ssh/id_ed25519
    cluster_key: inventories/site/files/cluster_ed25519.pub
    extra_devices: [lidar]
"""

RETURN = r"""
host_vars:
  description: The variables written to the robot's host_vars file.
  returned: success
  type: dict
  sample: {kuberos_fleet: test-fleet, kuberos_cpu: 4, kuberos_memory: 7812Mi, kuberos_gpu: 0, kuberos_arch: amd64,
           kuberos_devices: [camera, serial], kuberos_address: 192.0.2.19, ansible_host: 192.0.2.19, ansible_user: root}
host_vars_file:
  description: Path of the robot's host_vars file.
  returned: success
  type: str
registered_file:
  description: Path of the inventory file that lists the registered robots in the group robots.
  returned: success
  type: str
host_key_fingerprint:
  description: SHA256 fingerprint of the robot's host key.
  returned: success
  type: str
  sample: SHA256:n0l5Q7g6nqhGcS8mYpGcv0t2Vw8cQfOe0n0m4k8ZkxY
host_key_pinned:
  description: Whether this was the first contact, so the key is (or, in check mode, would be) pinned now.
  returned: success
  type: bool
cluster_key_installed:
  description: Whether the cluster's key was (or would be) appended to the robot's authorized_keys.
  returned: success
  type: bool
written:
  description: Files written (none in check mode).
  returned: success
  type: list
  elements: str
"""

from ansible.module_utils.basic import AnsibleModule, missing_required_lib

from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_ansible.python_packages import require_packages
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_ansible.results import fail
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_site import robot_registration
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_site.robot_registration import (
    DEFAULT_DEVICE_GLOBS,
    Registration,
    RegistrationError,
    Target,
)

ARGUMENT_SPEC = dict(
    name=dict(type="str", required=True),
    address=dict(type="str", required=True),
    port=dict(type="int", default=22),
    user=dict(type="str", default="root"),
    fleet=dict(type="str", required=True),
    inventory_dir=dict(type="path", required=True),
    known_hosts=dict(type="path", required=True),
    expected_fingerprint=dict(type="str", default=""),
    admin_key=dict(type="path", required=True),
    admin_key_passphrase=dict(type="str", no_log=True),
    cluster_key=dict(type="path", required=True),
    device_globs=dict(type="dict", default=DEFAULT_DEVICE_GLOBS),
    extra_devices=dict(type="list", elements="str", default=[]),
    connect_timeout=dict(type="float", default=10.0),
    command_timeout=dict(type="float", default=60.0),
)


def registration(params: dict) -> Registration:
    target = Target(
        robot=params["name"],
        address=params["address"],
        port=params["port"],
        user=params["user"],
        admin_key=params["admin_key"],
        known_hosts=params["known_hosts"],
        expected_fingerprint=params["expected_fingerprint"] or "",
        connect_timeout=params["connect_timeout"],
        command_timeout=params["command_timeout"],
        admin_key_passphrase=params["admin_key_passphrase"],
    )
    return Registration(
        robot=params["name"],
        address=params["address"],
        fleet=params["fleet"],
        inventory_dir=params["inventory_dir"],
        cluster_key=params["cluster_key"],
        target=target,
        device_globs=params["device_globs"],
        extra_devices=params["extra_devices"],
    )


def main():
    module = AnsibleModule(argument_spec=ARGUMENT_SPEC, supports_check_mode=True)
    require_packages(module, ["PyYAML"])
    if robot_registration.paramiko is None:
        module.fail_json(msg=missing_required_lib("paramiko"))
    try:
        result = robot_registration.register(registration(module.params), check_mode=module.check_mode)
    except RegistrationError as error:
        fail(module, error)
    diff = result.pop("diff")
    if module._diff:
        result["diff"] = diff
    module.exit_json(**result)


if __name__ == "__main__":
    main()
