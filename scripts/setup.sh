#!/usr/bin/env bash
# One-time set-up of a checkout: a Python 3.11 virtualenv with every pinned dependency (requirements.txt,
# requirements-ros.txt: ROS 2 from PyPI for the discovery tests, requirements-sim.txt: the simulator), and the
# link that lets Ansible find this checkout as the kuberos.platform collection. Idempotent.
set -euo pipefail
cd "$(dirname "$0")/.."

PYTHON="${PYTHON:-python3.11}"
command -v "$PYTHON" >/dev/null 2>&1 || PYTHON=python3
"$PYTHON" -c 'import sys; assert sys.version_info[:2] >= (3, 11), sys.version' || {
  echo "setup: Python 3.11 or newer is needed (found $("$PYTHON" --version 2>&1))" >&2
  exit 1
}

# Long steps print a line every 30 s (KUBEROS_PROGRESS_INTERVAL) and their time when they end.
# shellcheck source=SCRIPTDIR/../roles/local_cluster/files/progress.sh
source roles/local_cluster/files/progress.sh

# Installs the requirements file $1 (what they are: $2) into .venv.
pip_install() {
  echo "setup: installing $2 ($1)"
  with_progress "installing $1" -- .venv/bin/python -m pip install --quiet --progress-bar off -r "$1"
}

stamp=.venv/.requirements.sha256
want=$(cat requirements.txt requirements-ros.txt requirements-sim.txt | sha256sum | cut -d' ' -f1)
if [ ! -x .venv/bin/python ] || [ "$(cat "$stamp" 2>/dev/null)" != "$want" ]; then
  echo "setup: installing Python dependencies into .venv (first time: a few minutes, much longer on a busy machine)"
  with_progress "creating .venv" -- "$PYTHON" -m venv .venv
  with_progress "upgrading pip" -- .venv/bin/python -m pip install --quiet --upgrade pip
  pip_install requirements.txt "Ansible, the Kubernetes client and the test tools"
  pip_install requirements-ros.txt "ROS 2 (rclpy, Fast DDS) wheels for the discovery tests"
  pip_install requirements-sim.txt "the simulator's wheels (PyBullet, OMPL, toppra, matplotlib)"
  echo "$want" > "$stamp"
fi

# System programs of the network tests, installed when missing, as root with apt: namespaces and real pings;
# sshd, WireGuard (userspace wireguard-go: these kernels have no module) and ssh-keygen for the cluster
# setup roles' test hosts.
missing=()
command -v ip >/dev/null 2>&1 || missing+=(iproute2)
command -v ping >/dev/null 2>&1 || missing+=(iputils-ping)
[ -x /usr/sbin/sshd ] || missing+=(openssh-server)
command -v ssh >/dev/null 2>&1 || missing+=(openssh-client)
command -v wg >/dev/null 2>&1 || missing+=(wireguard-tools)
command -v wireguard-go >/dev/null 2>&1 || missing+=(wireguard-go)
command -v shellcheck >/dev/null 2>&1 || missing+=(shellcheck)  # ansible-test sanity's shellcheck test
# node_prereqs' packages: the role's test hosts have no route to package mirrors, so they are installed here.
# The local cluster's real nodes: CNI plugins, umoci and debootstrap to build the images they run, and the CNCF
# distribution registry (docker-registry) that serves them to the nodes. The lab machines of the kubeadm and site
# tests: systemd-nspawn (systemd-container) booting a debootstrap root, and a static busybox for their network checks;
# sudo for site.yml's become on the SSH lab hosts; keepalived for the virtual IP's test (three namespaces hold it).
for package in containerd runc conntrack socat iptables ethtool gpg containernetworking-plugins umoci debootstrap gcc libc6-dev \
  docker-registry systemd-container busybox-static sudo keepalived; do
  dpkg-query -W -f '${Status}' "$package" 2>/dev/null | grep -q 'install ok installed' || missing+=("$package")
done
if [ ${#missing[@]} -gt 0 ]; then
  if [ "$(id -u)" = 0 ] && command -v apt-get >/dev/null 2>&1; then
    echo "setup: installing ${missing[*]} (network namespace and latency probe tests)"
    with_progress "installing ${#missing[@]} Debian packages with apt-get" -- \
      bash -c 'apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq "$@" >/dev/null' apt "${missing[@]}" ||
      echo "setup: could not install ${missing[*]}; the tests that need them will be skipped" >&2
  else
    echo "setup: ${missing[*]} missing and not root with apt-get; the tests that need them will be skipped" >&2
  fi
fi

# The monitoring and dashboard tests: a real Prometheus (and promtool for the alerting rules) scrapes the controller,
# and a headless Chromium driven by chromedriver loads the dashboard. Without recommends: no node exporter, no desktop.
browser=()
command -v prometheus >/dev/null 2>&1 || browser+=(prometheus)
command -v chromium >/dev/null 2>&1 || browser+=(chromium)
command -v chromedriver >/dev/null 2>&1 || browser+=(chromium-driver)
if [ ${#browser[@]} -gt 0 ]; then
  if [ "$(id -u)" = 0 ] && command -v apt-get >/dev/null 2>&1; then
    echo "setup: installing ${browser[*]} (the monitoring and dashboard tests)"
    with_progress "installing ${#browser[@]} Debian packages with apt-get" -- \
      bash -c 'apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq --no-install-recommends "$@" >/dev/null' apt \
      "${browser[@]}" || echo "setup: could not install ${browser[*]}; the tests that need them will be skipped" >&2
  else
    echo "setup: ${browser[*]} missing and not root with apt-get; the tests that need them will be skipped" >&2
  fi
fi

mkdir -p .collections/ansible_collections/kuberos
ln -sfn ../../.. .collections/ansible_collections/kuberos/platform

# ansible-test sanity's tools (pylint, pycodestyle, yamllint, voluptuous... at the versions the installed ansible-core
# pins) from PyPI, into the virtualenvs it keeps under ~/.cache/kuberos/ansible-test (scripts/sanity.sh); once per
# ansible-core version. Without them the sanity test installs them when it runs.
sanity_home="${KUBEROS_CACHE_DIR:-$HOME/.cache/kuberos}/ansible-test"
sanity_stamp="$sanity_home/primed-$(.venv/bin/python -c 'import ansible.release; print(ansible.release.__version__)')"
if [ ! -e "$sanity_stamp" ]; then
  echo "setup: installing the tools of ansible-test sanity from PyPI (first time: about 4 minutes)"
  mkdir -p "$sanity_home"
  if scripts/sanity.sh --prime-venvs >"$sanity_home/prime.log" 2>&1; then
    touch "$sanity_stamp"
  else
    tail -20 "$sanity_home/prime.log" >&2
    echo "setup: could not install the tools of ansible-test sanity (log: $sanity_home/prime.log)" >&2
  fi
fi
echo "setup: ready (.venv, collection kuberos.platform linked from this checkout)"
