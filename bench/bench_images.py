#!/usr/bin/env python3
"""Images benchmark: the platform's images built here, served by the lab's registry, pulled by digest.

Each step timed from its start to its end, in one run:

(1) every image of ``local_images`` built cold (an empty cache), then again with nothing changed (warm); per image
    its archive size, digest and both times (the ROS image's cold time holds the shared base: debootstrap, the
    wheels, byte-compiling, packing; the published-layout image reuses that base);
(2) reproducibility: a second cold build in another empty cache; the same sources must give the same digests;
(3) the lab registry (``kuberos_lab.registry``: the CNCF distribution registry, TLS, htpasswd) on loopback: every
    image pushed by digest; a second push uploads nothing;
(4) cold pulls by digest over TLS with the password: for each of ``--nodes`` nodes a fresh containerd (its own
    root, as a node that never had the image) pulls and unpacks every image, in turn, as ``ctr images pull
    --hosts-dir`` (the registry's CA in a ``hosts.toml``, as the real nodes have it), timed per node and image.

Results print as Markdown and go to ``bench/results/images.json`` with ``--json`` (keys of issue 28: ``images``, a
list with ``name``, ``size_mib``, ``build_cold_s``, ``build_warm_s``, ``digest`` and ``pull_s`` per node). As root.

    .venv/bin/python bench/bench_images.py --json bench/results/images.json
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time

from bench_deploy import REPO, log, machine

sys.path[:0] = [str(REPO / ".collections")]
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_lab import local_images  # noqa: E402
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_lab.registry import LocalRegistry, lab_repository  # noqa: E402

CONTAINERD = """version = 2
root = "{d}/root"
state = "{d}/state"
[grpc]
  address = "{d}/containerd.sock"
[plugins."io.containerd.internal.v1.opt"]
  path = "{d}/opt"
"""


def build(cache: str) -> list[dict]:
    return local_images._build(str(REPO), cache, log=log)  # the per-image results: reference, archive, seconds


def free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


def cold_pull(directory: str, registry: LocalRegistry, references: list[str]) -> dict[str, float]:
    """A containerd of its own under ``directory`` pulls each reference (nothing cached): seconds per reference."""
    os.makedirs(directory)
    config = os.path.join(directory, "config.toml")
    with open(config, "w", encoding="utf-8") as handle:
        handle.write(CONTAINERD.format(d=directory))
    hosts = os.path.join(directory, "certs.d", registry.address)
    os.makedirs(hosts)
    with open(os.path.join(hosts, "hosts.toml"), "w", encoding="utf-8") as handle:
        handle.write(registry.containerd_hosts())
    address = os.path.join(directory, "containerd.sock")
    with open(os.path.join(directory, "log"), "wb") as output:
        daemon = subprocess.Popen(
            ["containerd", "--config", config], stdout=output, stderr=subprocess.STDOUT, start_new_session=True
        )
    seconds = {}
    try:
        deadline = time.monotonic() + 30
        while subprocess.run(["ctr", "-a", address, "version"], capture_output=True).returncode != 0:
            if time.monotonic() > deadline or daemon.poll() is not None:
                raise SystemExit(f"bench: containerd did not start ({directory}/log)")
            time.sleep(0.2)
        for reference in references:
            started = time.monotonic()
            subprocess.run(
                ["ctr", "-a", address, "-n", "bench", "images", "pull", "--hosts-dir", os.path.join(directory, "certs.d"),
                 "--user", f"{registry.username}:{registry.password}", reference],
                check=True, capture_output=True, timeout=900,
            )  # fmt: skip
            seconds[reference] = round(time.monotonic() - started, 1)
    finally:
        os.killpg(daemon.pid, signal.SIGTERM)
        daemon.wait(timeout=30)
        for line in reversed(open("/proc/self/mounts", encoding="utf-8").read().splitlines()):
            point = line.split()[1]
            if point.startswith(directory):
                subprocess.run(["umount", "-l", point], check=False)
        shutil.rmtree(directory, ignore_errors=True)
    return seconds


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--nodes", type=int, default=4, help="fresh containerds that pull every image [%(default)s]")
    parser.add_argument("--no-reproducibility", action="store_true", help="skip the second cold build")
    parser.add_argument("--json", help="write the results here")
    args = parser.parse_args()
    if os.geteuid() != 0:
        raise SystemExit("bench: building images needs root (debootstrap, chroot)")
    results: dict = {"machine": machine(), "command": " ".join(sys.argv)}
    work = tempfile.mkdtemp(prefix="kuberos-bench-images-")
    try:
        log("(1) cold build into an empty cache")
        cold = build(os.path.join(work, "cold"))
        log("(1) warm build: nothing changed")
        warm = {r["reference"]: r for r in build(os.path.join(work, "cold"))}
        images = []
        for result in cold:
            name, digest = local_images.archive_image(result["archive"])
            images.append(
                {
                    "name": name,
                    "size_mib": round(result["bytes"] / 2**20, 1),
                    "build_cold_s": result["seconds"],
                    "build_warm_s": warm[result["reference"]]["seconds"],
                    "digest": digest,
                    "archive": result["archive"],
                }
            )
        if not args.no_reproducibility:
            log("(2) a second cold build into another empty cache")
            again = {r["reference"]: local_images.archive_image(r["archive"])[1] for r in build(os.path.join(work, "again"))}
            for image in images:
                image["same_digest_when_rebuilt"] = again.get(image["name"]) == image["digest"]
            results["reproducible"] = all(image["same_digest_when_rebuilt"] for image in images)
            shutil.rmtree(os.path.join(work, "again"), ignore_errors=True)

        log("(3) the lab registry on loopback; push by digest")
        registry = LocalRegistry(os.path.join(work, "registry"), "127.0.0.1", free_port())
        registry.start()
        try:
            client = registry.client()
            for image in images:
                repository, tag = lab_repository(image["name"])
                started = time.monotonic()
                digest, done = client.push_archive(image["archive"], repository, tag)
                image["push_s"] = round(time.monotonic() - started, 1)
                assert digest == image["digest"], (digest, image)
                _digest, again_done = client.push_archive(image["archive"], repository)
                image["second_push_uploaded"] = again_done["uploaded"]
                image["reference"] = f"{registry.address}/{repository}@{digest}"
                log(f"pushed {image['reference']} in {image['push_s']} s ({done['uploaded']} blobs)")
            log(f"(4) cold pulls by digest into {args.nodes} fresh containerds, in turn")
            for node in range(1, args.nodes + 1):
                pulled = cold_pull(os.path.join(work, f"node-{node}"), registry, [i["reference"] for i in images])
                for image in images:
                    image.setdefault("pull_s", {})[f"node-{node}"] = pulled[image["reference"]]
                log(f"node-{node}: {pulled}")
        finally:
            registry.stop(remove=True)
        for image in images:
            del image["archive"]
        results["images"] = images
    finally:
        shutil.rmtree(work, ignore_errors=True)

    print("| image | MiB | cold build s | warm s | push s | cold pull s per node | same digest rebuilt |")
    print("|---|---|---|---|---|---|---|")
    for image in results["images"]:
        pulls = ", ".join(f"{v}" for v in image["pull_s"].values())
        print(f"| `{image['name']}` | {image['size_mib']} | {image['build_cold_s']} | {image['build_warm_s']} | "
              f"{image['push_s']} | {pulls} | {image.get('same_digest_when_rebuilt', '-')} |")  # fmt: skip
    if args.json:
        os.makedirs(os.path.dirname(args.json) or ".", exist_ok=True)
        previous = {}
        if os.path.exists(args.json):
            with open(args.json, encoding="utf-8") as handle:
                previous = json.load(handle)
        with open(args.json, "w", encoding="utf-8") as handle:
            json.dump({**previous, **results}, handle, indent=1)
            handle.write("\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
