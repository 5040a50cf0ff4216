"""playbooks/deploy.yml and batch.yml with manifests of the reference KubeROS format, render-only on the embedded
inventory (inventories/local), with ansible-playbook as a user runs it: the application renders and says what it
ignored, a rerun changes nothing, a reference BatchJob renders its Jobs through deploy.yml, and a broken manifest is
refused naming the file, line and reference field, with nothing written."""

from __future__ import annotations

import os
import shutil

import pytest
from helpers import ROOT, playbook

pytestmark = pytest.mark.playbook

APP = os.path.join(ROOT, "examples", "reference", "talker-listener.kuberos.yml")
BATCH = os.path.join(ROOT, "examples", "reference", "grid.batchjob.yml")


def render(name, spec, out, *extra):
    return playbook(
        name, "-e", f"rosdeployment_file={spec}", "-e", f"kuberos_render_dir={out}", "-e", "kuberos_apply=false", *extra
    )


def files(out):
    return sorted(
        os.path.relpath(os.path.join(d, n), out) for d, _dirs, names in os.walk(os.path.join(out, "manifests")) for n in names
    )


def test_a_reference_application_renders_and_says_what_it_ignored(tmp_path):
    out = tmp_path / "app"
    first = render("deploy.yml", APP, out)
    assert first.returncode == 0, first.stdout[-4000:] + first.stderr[-2000:]
    assert first.changed == 1
    assert "rosModules[0].requirements.dynamicRescheduling" in first.stdout  # the notes task
    assert "talker-listener     fetch-1  talker               onboard  fetch-1" in first.stdout
    rendered = files(out)
    for name in (
        "configmap-talker-listener-map-talker-launch.yaml",
        "deployment-talker-listener-talker-fetch-1.yaml",
        "deployment-talker-listener-listener-fetch-1.yaml",
    ):
        assert f"manifests/kuberos-test-fleet/{name}" in rendered
    talker = (out / "manifests" / "kuberos-test-fleet" / "deployment-talker-listener-talker-fetch-1.yaml").read_text()
    assert "gripper_port:=/dev/ttyUSB0 topic:=/chatter" in talker  # fetch-1's gripper, from the inventory
    again = render("deploy.yml", APP, out)
    assert again.returncode == 0 and again.changed == 0, again.stdout[-3000:]


def test_a_reference_batch_job_renders_through_the_deploy_playbook(tmp_path):
    out = tmp_path / "batch"
    result = render("deploy.yml", BATCH, out)
    assert result.returncode == 0, result.stdout[-4000:] + result.stderr[-2000:]
    assert "a batch job of 12 runs" in result.stdout and "metadata.subname" in result.stdout
    jobs = [f for f in files(out) if "/job-" in f]
    assert len(jobs) == 6 and (out / "plan.txt").exists()
    same = render("batch.yml", BATCH, tmp_path / "batch2")
    assert same.returncode == 0, same.stdout[-3000:]
    assert files(tmp_path / "batch2") == files(out)


def test_a_broken_reference_manifest_names_its_fields_and_writes_nothing(tmp_path):
    text = open(APP, encoding="utf-8").read()
    text = text.replace("latency: 20ms", "latency: soon").replace("type: key-value\n    data:", "type: table\n    data:")
    spec = tmp_path / "broken.kuberos.yml"
    spec.write_text(text, encoding="utf-8")
    shutil.copytree(os.path.join(ROOT, "examples", "reference", "config"), tmp_path / "config")
    out = tmp_path / "out"
    result = render("deploy.yml", spec, out)
    assert result.returncode != 0
    assert f"{spec}:24: rosModules[0].requirements.latency: 'soon' is not valid" in result.stdout, result.stdout[-3000:]
    assert f"{spec}:48: rosParamMap[0].type: 'table' is not valid; expected key-value or yaml" in result.stdout
    assert "Traceback" not in result.stdout + result.stderr
    assert not out.exists()
