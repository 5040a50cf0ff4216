"""The pick-and-place RosDeployment both benchmarks use (the modules of examples/pick-and-place.yml,
sized for large synthetic fleets)."""

from __future__ import annotations


def pick_and_place(name: str, fleet: str, coordinator: str = "shared", robots_per_instance: int = 4) -> dict:
    """Perception (edge, then cloud, within 20 ms), motion planner (cloud within 200 ms), controller
    (onboard, needs a gripper) and a task coordinator, ``shared`` by ``robots_per_instance`` robots or
    ``dedicated`` (one per robot)."""
    task_coordinator = {
        "name": "task-coordinator",
        "image": "ghcr.io/kuberos/pnp-coordinator:0.1",
        "launch": ["ros2 run kuberos_pnp coordinator"],
        "preference": "edge",
        "strategy": coordinator,
        "resources": {"cpu": "100m", "memory": "128Mi"},
        "env": {"LOG_LEVEL": "info"},
    }
    if coordinator == "shared":
        task_coordinator["robotsPerInstance"] = robots_per_instance
    return {
        "apiVersion": "kuberos.io/v1alpha1",
        "kind": "RosDeployment",
        "metadata": {"name": name, "targetFleet": fleet, "labels": {"app.kubernetes.io/part-of": name}},
        "rosDomainId": 7,
        "discovery": {"servers": 2},
        "rosModules": [
            {
                "name": "perception",
                "image": "ghcr.io/kuberos/pnp-perception:0.1",
                "launch": ["ros2 launch kuberos_pnp perception.launch.py"],
                "preference": ["edge", "cloud"],
                "requirements": {"max_latency": "20 ms", "arch": "amd64"},
                "resources": {"cpu": "500m", "memory": "512Mi"},
                "rosParameters": {"voxel_size": 0.01, "camera_topic": "/head_camera/depth"},
            },
            {
                "name": "motion-planner",
                "image": "ghcr.io/kuberos/pnp-planner:0.1",
                "launch": ["ros2 launch kuberos_pnp planner.launch.py"],
                "preference": "cloud",
                "requirements": {"max_latency": "200 ms"},
                "resources": {"cpu": "500m", "memory": "512Mi"},
                "rosParameters": {"planner": "RRTConnect", "planning_time": 2.0},
            },
            {
                "name": "controller",
                "image": "ghcr.io/kuberos/pnp-control:0.1",
                "launch": ["ros2 launch kuberos_pnp control.launch.py"],
                "requirements": {"onboard": True, "devices": ["gripper"]},
                "resources": {"cpu": "500m", "memory": "512Mi"},
            },
            task_coordinator,
        ],
    }
