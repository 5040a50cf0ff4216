"""Batch jobs: a grid of parameter values, every combination run ``repeat`` times, as Kubernetes Jobs.

A batch job is a RosDeployment (modules, parameter maps, registries, middleware) with a ``job`` section
(docs/batch.md): ``grid`` lists keys of key-value parameter maps and the values each takes, and every combination
of them is one run of the deployment's modules. The lifecycle ``module`` decides when a run ends (when it exits);
the other modules run beside it in the same pod (native sidecars, stopped when it ends), so the modules of a run
find one another on localhost only and runs never see each other.

- One indexed Job per combination, ``<job>-<n>``: ``completions`` = ``repeat``, one at a time, each index one
  run (``JOB_COMPLETION_INDEX``), ``backoffLimitPerIndex: 0`` (a failed run is a result, not retried, and the
  next repeat still runs); the pod's ``activeDeadlineSeconds`` is the running timeout.
- ``parallelism`` combinations run at once, in waves: combination ``n`` runs in wave ``n // parallelism`` on slot
  ``n % parallelism``. Each slot is one node, chosen by the scheduler (``place_modules``) for the run's combined
  resources and the lifecycle module's preference and requirements, as if the run were a module of a robot
  (the job's robots in turn).
- The reference format's ``kind: BatchJob`` (``jobSpec``: ``varyingParameters``, ``lifecycleModule``,
  ``startupTimeout``, ``runningTimeout``) is translated into this, with notes.

Pure: no Ansible, no Kubernetes, no I/O.
"""

from __future__ import annotations

import copy
import functools
import itertools
import json
from dataclasses import dataclass, field, replace

from . import naming, quantities, reference_format
from .errors import Problem, SpecError, describe
from .labels import COMPONENT, MANAGED_BY
from .manifests import RenderOptions, fleet_policies, module_pod
from .placement import Instance
from .schema import DNS_LABEL, MAP_NAME
from .spec import BATCH_KINDS, LaunchArgument, Resources, RosDeployment, RosModule, _env_value, _parse_any, _parse_document
from .validation import schema_problems, strict_validator
from .yaml_source import Document, format_path, load_documents, path_prefix

KIND, REFERENCE_KIND = BATCH_KINDS
ANY_FLEET = "kuberos-any-fleet"  # a batch job that names no fleet runs in the inventory's first fleet
BATCH = "kuberos.io/batch"
RUN = "kuberos.io/batch-run"
WAVE_ANNOTATION = "kuberos.io/batch-wave"
PARAMETERS_ANNOTATION = "kuberos.io/batch-parameters"
MAX_RUNS = 10000  # combinations x repeats of one job
DEFAULT_STARTUP_S = 300.0
DEFAULT_RUNNING_S = 3600.0
_DURATION = {"type": ["string", "number"], "x-expected": "a duration such as '120 s' or '20 min' (a number means seconds)"}
JOB_SCHEMA = {
    "type": "object",
    "x-expected": "a mapping with module, grid, repeat, parallelism and timeouts",
    "additionalProperties": False,
    "required": ["module"],
    "properties": {
        "module": {"type": "string", "pattern": DNS_LABEL, "x-expected": "the name of one of rosModules"},
        "repeat": {"type": "integer", "minimum": 1, "maximum": MAX_RUNS, "x-expected": f"a whole number from 1 to {MAX_RUNS}"},
        "parallelism": {"type": "integer", "minimum": 1, "maximum": 100, "x-expected": "a whole number from 1 to 100"},
        "startupTimeout": _DURATION,
        "runningTimeout": _DURATION,
        "grid": {
            "type": "array",
            "maxItems": 20,
            "x-expected": "a list of parameters with map, key and values",
            "items": {
                "type": "object",
                "x-expected": "a mapping with map, key and values",
                "additionalProperties": False,
                "required": ["map", "key", "values"],
                "properties": {
                    "map": {"type": "string", "pattern": MAP_NAME, "x-expected": "a key-value parameter map"},
                    "key": {"type": "string", "minLength": 1, "maxLength": 253, "x-expected": "a key of that map"},
                    "values": {
                        "type": "array",
                        "minItems": 1,
                        "maxItems": MAX_RUNS,
                        "items": {"type": ["string", "number", "boolean"], "x-expected": "a value"},
                        "x-expected": "a non-empty list of values",
                    },
                },
            },
        },
    },
}


@functools.cache
def _validator():
    return strict_validator({"type": "object", "properties": {"job": JOB_SCHEMA}})


@dataclass(frozen=True)
class GridAxis:
    map: str
    key: str
    values: tuple[str, ...]


@dataclass(frozen=True)
class BatchJob:
    name: str
    deployment: RosDeployment  # the modules and maps of one run, before the grid's values
    module: str  # the lifecycle module
    repeat: int = 1
    parallelism: int = 0  # 0: every combination at once
    startup_timeout_s: float = DEFAULT_STARTUP_S
    running_timeout_s: float = DEFAULT_RUNNING_S
    grid: tuple[GridAxis, ...] = ()
    source: str = "<batch job>"
    kind: str = KIND
    notes: tuple[str, ...] = field(default=(), compare=False)

    @property
    def fleet(self) -> str:
        return self.deployment.fleet

    def combinations(self) -> list[tuple[tuple[str, str, str], ...]]:
        """Every combination of the grid's values, in order: ((map, key, value), ...) each."""
        axes = [[(a.map, a.key, v) for v in a.values] for a in self.grid]
        return [tuple(c) for c in itertools.product(*axes)] if axes else [()]

    @property
    def slots(self) -> int:
        count = len(self.combinations())
        return min(self.parallelism or count, count)

    def run_deployment(self, number: int) -> RosDeployment:
        """Combination ``number``'s deployment: its values in the maps, launch arguments taken from them again."""
        values = {(m, k): v for m, k, v in self.combinations()[number]}
        maps = tuple(
            replace(p, values=tuple((k, values.get((p.name, k), v)) for k, v in p.values)) if p.type == "key-value" else p
            for p in self.deployment.parameter_maps
        )
        by_name = {p.name: p for p in maps}

        def argument(a: LaunchArgument) -> LaunchArgument:
            return replace(a, value=by_name[a.map].value(a.key)) if a.map else a

        modules = tuple(
            replace(m, launch_arguments=tuple(argument(a) for a in m.launch_arguments)) for m in self.deployment.modules
        )
        return replace(self.deployment, name=run_name(self.name, number), parameter_maps=maps, modules=modules)


def run_name(job: str, number: int) -> str:
    return naming.dns_label(job, str(number), max_len=52)


def _seconds(raw, default: float, doc: Document, parts: tuple, problems: list[Problem]) -> float:
    if raw is None:
        return default
    try:
        seconds = float(raw) if isinstance(raw, (int, float)) and not isinstance(raw, bool) else _text_seconds(str(raw))
    except ValueError as exc:
        problems.append(
            Problem(doc.source, ".".join(map(str, parts)), f"{describe(raw)} is not valid; {exc}", doc.line_of(parts))
        )
        return default
    if seconds <= 0:
        problems.append(Problem(doc.source, ".".join(map(str, parts)), "must be more than zero", doc.line_of(parts)))
    return seconds


def _text_seconds(text: str) -> float:
    stripped = text.strip()
    for unit, factor in (("min", 60.0), ("h", 3600.0)):
        if stripped.endswith(unit) and stripped[: -len(unit)].strip().replace(".", "", 1).isdigit():
            return float(stripped[: -len(unit)]) * factor
    if stripped.replace(".", "", 1).isdigit():
        return float(stripped)
    return quantities.parse_latency_ms(stripped) / 1000.0


def _job_problems(job: dict, dep: RosDeployment, doc: Document, base: tuple) -> list[Problem]:
    """What the job section says that the deployment contradicts: the lifecycle module, the grid's maps and keys."""
    problems = []

    def add(parts, message):
        problems.append(Problem(doc.source, _path((*base, *parts)), message, doc.line_of((*base, *parts))))

    names = [m.name for m in dep.modules]
    if job["module"] not in names:
        add(("module",), f"'{job['module']}' is not one of rosModules ({', '.join(names)}); expected the lifecycle module")
    seen = set()
    for index, axis in enumerate(job.get("grid") or ()):
        pmap = dep.parameter_map(axis["map"])
        if pmap is None or pmap.type != "key-value":
            add(("grid", index, "map"), f"'{axis['map']}' is not a key-value parameter map of the job")
        elif pmap.value(axis["key"]) is None:
            add(
                ("grid", index, "key"),
                f"parameter map {axis['map']} has no key {axis['key']!r}; its keys: "
                + ", ".join(key for key, _value in pmap.values),
            )
        if (axis["map"], axis["key"]) in seen:
            add(("grid", index), f"{axis['map']}.{axis['key']} is already varied; expected each key once")
        seen.add((axis["map"], axis["key"]))
    return problems


def _path(parts) -> str:
    return format_path(parts)


def _parse_ours(doc: Document, catalog, read_file) -> BatchJob:
    data = doc.data
    problems = schema_problems(_validator(), doc)
    job = data.get("job")
    if not isinstance(job, dict):
        problems.append(
            Problem(
                doc.source, "job", f"{describe(job)} is not valid; expected a mapping with module and grid", doc.line_of(("job",))
            )
        )
    rest = {k: v for k, v in data.items() if k != "job"}
    rest["kind"] = "RosDeployment"
    metadata = rest.get("metadata")
    if isinstance(metadata, dict) and "targetFleet" not in metadata:
        rest["metadata"] = {**metadata, "targetFleet": ANY_FLEET}
    try:
        dep = _parse_document(Document(rest, doc.source, doc.index, doc.lines), catalog, read_file)
    except SpecError as exc:
        problems.extend(exc.problems)
        dep = None
    if problems:
        raise SpecError(problems, title=f"{doc.source} is not a valid {KIND}")
    return _batch_job(job, dep, doc, ("job",), KIND, ())


def _batch_job(job: dict, dep: RosDeployment, doc: Document, base: tuple, kind: str, notes: tuple) -> BatchJob:
    """The job, or SpecError; ``base`` is where the job section is (``job``, or the reference's ``jobSpec``, whose
    problems are renamed to the reference's fields)."""
    try:
        return _checked_job(job, dep, doc, base, kind, notes)
    except SpecError as exc:
        if kind != REFERENCE_KIND:
            raise
        renamed = [replace(p, path=_reference_path("job" + p.path[len("jobSpec") :])) for p in exc.problems]
        raise SpecError(renamed, title=exc.title) from None


def _checked_job(job: dict, dep: RosDeployment, doc: Document, base: tuple, kind: str, notes: tuple) -> BatchJob:
    problems = _job_problems(job, dep, doc, base)
    startup = _seconds(job.get("startupTimeout"), DEFAULT_STARTUP_S, doc, (*base, "startupTimeout"), problems)
    running = _seconds(job.get("runningTimeout"), DEFAULT_RUNNING_S, doc, (*base, "runningTimeout"), problems)
    grid = tuple(
        GridAxis(a["map"], a["key"], tuple(dict.fromkeys(_env_value(v) for v in a["values"]))) for a in job.get("grid") or ()
    )
    batch = BatchJob(
        name=dep.name,
        deployment=dep,
        module=job["module"],
        repeat=int(job.get("repeat", 1)),
        parallelism=int(job.get("parallelism", 0)),
        startup_timeout_s=startup,
        running_timeout_s=running,
        grid=grid,
        source=doc.source,
        kind=kind,
        notes=tuple(notes) + dep.notes,
    )
    runs = len(batch.combinations()) * batch.repeat
    if runs > MAX_RUNS:
        problems.append(
            Problem(
                doc.source,
                _path((*base, "grid")),
                f"makes {runs} runs; expected at most {MAX_RUNS}",
                doc.line_of((*base, "grid")),
            )
        )
    if problems:
        raise SpecError(problems, title=f"{doc.source} is not a valid {kind}")
    return batch


REFERENCE_JOB_NOTES = {
    "volumes": (
        "results are each run's termination message and logs, collected into the render directory; "
        "mount a volume with the module instead"
    ),
    "volume": (
        "results are each run's termination message and logs, collected into the render directory; "
        "mount a volume with the module instead"
    ),
    "resources": "a run requests its modules' resources",
    "advances": "not used",
    "maxRetry": "a failed run is a result and is not retried",
}


def _parse_reference(doc: Document, catalog, read_file) -> BatchJob:
    """``kind: BatchJob``: metadata.name and subname, jobSpec, rosModules and rosParamMap of the reference format."""
    data = doc.data
    notes: list[str] = []
    problems: list[Problem] = []
    where = doc.source

    def note(parts, message):
        line = doc.line_of(parts)
        notes.append(f"{where}:{line}: {_path(parts)}: {message}" if line else f"{where}: {_path(parts)}: {message}")

    metadata = data.get("metadata") if isinstance(data.get("metadata"), dict) else {}
    spec = data.get("jobSpec")
    if not isinstance(spec, dict):
        raise SpecError(
            [
                Problem(
                    where,
                    "jobSpec",
                    f"{describe(spec)} is not valid; expected a mapping with lifecycleModule",
                    doc.line_of(("jobSpec",)),
                )
            ]
        )
    name = "-".join(str(p) for p in (metadata.get("name"), metadata.get("subname")) if p)
    dns = naming.dns_label(name.lower().replace("_", "-"), max_len=40) if name else ""
    if dns != name:
        note(
            ("metadata", "subname" if metadata.get("subname") else "name"),
            f"the job is named {dns!r} (name and subname, as a Kubernetes name)",
        )
    for key in ("execClusters", "useRobotResource", "description"):
        if key in metadata:
            note(
                ("metadata", key),
                {
                    "execClusters": "not used: the runs go to the fleet's nodes of the cluster this collection deploys to",
                    "useRobotResource": "the lifecycle module's preference decides where runs go",
                    "description": "informational",
                }[key],
            )
    translated = {
        "apiVersion": "v1",
        "kind": reference_format.KIND,
        "metadata": {"name": dns or metadata.get("name"), "targetFleet": metadata.get("targetFleet", ANY_FLEET)},
        **{k: data[k] for k in ("rosModules", "rosParamMap", "containerRegistry") if k in data},
    }
    for key in ("targetRobots", "edgeResourceGroup", "rmwImplementation", "rosVersion", "appVersion"):
        if key in metadata:
            translated["metadata"][key] = metadata[key]
    dep = _parse_any(Document(translated, where, doc.index, doc.lines), catalog, read_file)
    lifecycle = spec.get("lifecycleModule") if isinstance(spec.get("lifecycleModule"), dict) else {}
    job = {"module": reference_format.module_name(lifecycle.get("rosModuleName")), "repeat": lifecycle.get("repeatNum", 1)}
    if "startupTimeout" in spec:
        job["startupTimeout"] = spec["startupTimeout"]
    if "runningTimeout" in spec:
        job["runningTimeout"] = spec["runningTimeout"]
    if "maxParallelism" in spec:
        job["parallelism"] = spec["maxParallelism"]
    grid = []
    for index, axis in enumerate(spec.get("varyingParameters") or ()):
        if not isinstance(axis, dict):
            problems.append(
                Problem(
                    where,
                    f"jobSpec.varyingParameters[{index}]",
                    f"{describe(axis)} is not valid; expected toRosParamMap, paramName and valueList",
                    doc.line_of(("jobSpec", "varyingParameters", index)),
                )
            )
            continue
        grid.append({"map": axis.get("toRosParamMap"), "key": axis.get("paramName"), "values": axis.get("valueList")})
    if grid:
        job["grid"] = grid
    for key in spec:
        if key in REFERENCE_JOB_NOTES:
            note(("jobSpec", key), REFERENCE_JOB_NOTES[key])
        elif key not in ("startupTimeout", "runningTimeout", "maxParallelism", "varyingParameters", "lifecycleModule"):
            note(("jobSpec", key), "is not a field of the reference jobSpec; ignored")
    found = schema_problems(_validator(), Document({"job": job}, where, doc.index, {}))
    problems.extend(replace(p, path=_reference_path(p.path), line=doc.line_of(("jobSpec",))) for p in found)
    if problems:
        raise SpecError(problems, title=f"{where} is not a valid {REFERENCE_KIND}")
    return _batch_job(job, dep, doc, ("jobSpec",), REFERENCE_KIND, tuple(notes))


REFERENCE_FIELDS = {
    "job.module": "jobSpec.lifecycleModule.rosModuleName",
    "job.repeat": "jobSpec.lifecycleModule.repeatNum",
    "job.parallelism": "jobSpec.maxParallelism",
    "job.grid": "jobSpec.varyingParameters",
    "job": "jobSpec",
}


def _reference_path(path: str) -> str:
    prefix = path_prefix(path, REFERENCE_FIELDS)
    if prefix is None:
        return path
    path = REFERENCE_FIELDS[prefix] + path[len(prefix) :]
    return path.replace(".map", ".toRosParamMap").replace(".key", ".paramName").replace(".values", ".valueList")


def is_batch_document(data) -> bool:
    return isinstance(data, dict) and data.get("kind") in (KIND, REFERENCE_KIND)


def load_batch_jobs(text: str, source: str = "<batch job>", catalog=None, read_file=None, documents=None) -> list[BatchJob]:
    """Every batch job of a file (``RosBatchJob`` or the reference's ``BatchJob``); every problem at once.
    ``documents``: the file's documents when the caller has read them from ``text`` already."""
    documents = [d for d in (load_documents(text, source) if documents is None else documents) if d.data is not None]
    jobs, problems = [], []
    for doc in documents:
        if len(documents) > 1:
            doc.source = f"{source} (document {doc.index + 1})"
        if not is_batch_document(doc.data):
            problems.append(
                Problem(
                    doc.source,
                    "kind",
                    f"{describe(doc.data.get('kind') if isinstance(doc.data, dict) else doc.data)} is not a batch job; "
                    f"expected kind {KIND} (or the reference format's {REFERENCE_KIND}); a RosDeployment deploys with "
                    "playbooks/deploy.yml",
                    doc.line_of(("kind",)),
                )
            )
            continue
        try:
            parse = _parse_ours if doc.data["kind"] == KIND else _parse_reference
            jobs.append(parse(doc, catalog, read_file))
        except SpecError as exc:
            problems.extend(exc.problems)
    if not documents:
        problems.append(Problem(source, "", "no batch job found; the file is empty"))
    if problems:
        raise SpecError(problems, title=f"{source} is not a valid batch job")
    return jobs


# --- placement ----------------------------------------------------------------------------------------------------


def with_fleet(job: BatchJob, fleets: list[str]) -> BatchJob:
    """The job in its fleet: the one it names, or (naming none) the first of ``fleets``, noted."""
    if job.fleet != ANY_FLEET:
        return job
    if not fleets:
        raise SpecError([Problem(job.source, "metadata.targetFleet", "is not given and the inventory has no fleet")])
    fleet = sorted(fleets)[0]
    note = f"{job.source}: metadata.targetFleet: not given; the runs go to fleet {fleet}, the inventory's first"
    return replace(job, deployment=replace(job.deployment, fleet=fleet), notes=(*job.notes, note))


def run_unit(job: BatchJob) -> RosModule:
    """One run as the scheduler sees it: the lifecycle module with every module's resources and devices."""
    modules = job.deployment.modules
    lifecycle = next(m for m in modules if m.name == job.module)
    devices = tuple(dict.fromkeys(d for m in modules for d in m.requirements.devices))
    return replace(
        lifecycle,
        strategy="dedicated",
        scaling=None,
        requirements=replace(lifecycle.requirements, devices=devices),
        resources=Resources(
            sum(m.resources.cpu_millis for m in modules),
            sum(m.resources.memory_bytes for m in modules),
            sum(m.resources.gpu for m in modules),
        ),
    )


def slot_deployments(job: BatchJob, robots: list[str]) -> list[RosDeployment]:
    """One deployment per slot, of one robot each (the job's robots in turn), for ``place_modules``."""
    unit = run_unit(job)
    return [
        replace(
            job.deployment,
            name=naming.dns_label(job.name, f"slot-{i}", max_len=40),
            robots=(robots[i % len(robots)],),
            modules=(unit,),
            parameter_maps=(),
        )
        for i in range(job.slots)
    ]


# --- rendering ----------------------------------------------------------------------------------------------------


def _sidecar(container: dict, prefix: str) -> dict:
    """A module beside the lifecycle module: a native sidecar (stopped when the run ends), its volumes prefixed."""
    out = copy.deepcopy(container)
    out["restartPolicy"] = "Always"
    for mount in out.get("volumeMounts", []):
        mount["name"] = f"{prefix}-{mount['name']}"
    return out


def render_batch(job: BatchJob, slots: list[Instance], options: RenderOptions | None = None) -> list[dict]:
    """Every object of the job: per combination its parameter maps and its indexed Job on its slot's node."""
    options = options or RenderOptions()
    namespace = naming.fleet_namespace(job.fleet)
    labels = {MANAGED_BY: "kuberos", COMPONENT: "batch-run", BATCH: job.name}
    from .manifests import parameter_map_configmap

    objects = []
    for number, combination in enumerate(job.combinations()):
        dep = job.run_deployment(number)
        slot = slots[number % len(slots)]
        run_labels = {**labels, RUN: str(number)}
        objects.extend(parameter_map_configmap(dep, p, run_labels) for p in dep.parameter_maps)
        parameters = json.dumps({f"{m}.{k}": v for m, k, v in combination}, sort_keys=True)
        pods = []
        for module in dep.modules:
            inst = replace(
                slot,
                name=dep.name,
                deployment=dep.name,
                module=module.name,
                cpu_millis=module.resources.cpu_millis,
                memory_bytes=module.resources.memory_bytes,
                gpu=module.resources.gpu,
            )
            pods.append((module, module_pod(dep, module, inst, None, dict(run_labels), options)))
        (main_module, main), *others = sorted(pods, key=lambda pair: pair[0].name != job.module)
        spec = main["spec"]
        extra_env = [
            {"name": "KUBEROS_BATCH_JOB", "value": job.name},
            {"name": "KUBEROS_BATCH_RUN", "value": str(number)},
            {"name": "KUBEROS_BATCH_PARAMETERS", "value": parameters},
        ]
        for container in spec["containers"]:
            container["env"].extend(copy.deepcopy(extra_env))
            container["terminationMessagePolicy"] = "FallbackToLogsOnError"
        for module, pod in others:
            for container in pod["spec"]["containers"]:
                container["env"].extend(copy.deepcopy(extra_env))
                spec.setdefault("initContainers", []).append(_sidecar(container, module.name))
            for volume in pod["spec"].get("volumes", []):
                spec.setdefault("volumes", []).append({**volume, "name": f"{module.name}-{volume['name']}"})
            for secret in pod["spec"].get("imagePullSecrets", []):
                if secret not in spec.setdefault("imagePullSecrets", []):
                    spec["imagePullSecrets"].append(secret)
        spec["restartPolicy"] = "Never"
        spec["activeDeadlineSeconds"] = max(1, round(job.running_timeout_s))
        main["metadata"].setdefault("annotations", {})[PARAMETERS_ANNOTATION] = parameters
        objects.append(
            {
                "apiVersion": "batch/v1",
                "kind": "Job",
                "metadata": {
                    "name": dep.name,
                    "namespace": namespace,
                    "labels": run_labels,
                    "annotations": {
                        WAVE_ANNOTATION: str(number // len(slots)),
                        PARAMETERS_ANNOTATION: parameters,
                        "kuberos.io/node": slot.node,
                        "kuberos.io/lifecycle-module": main_module.name,
                    },
                },
                "spec": {
                    "completions": job.repeat,
                    "parallelism": 1,
                    "completionMode": "Indexed",
                    "backoffLimitPerIndex": 0,
                    "maxFailedIndexes": job.repeat,
                    "template": main,
                },
            }
        )
    # the fleet's isolation, as its deployments render it: a run's pod talks to itself only (localhost discovery)
    return fleet_policies(job.fleet) + objects


def waves(job: BatchJob) -> list[list[int]]:
    """The combinations of each wave, in order."""
    count, size = len(job.combinations()), job.slots
    return [list(range(start, min(start + size, count))) for start in range(0, count, size)]


__all__ = ["BatchJob", "GridAxis", "load_batch_jobs", "render_batch", "run_unit", "slot_deployments", "waves", "with_fleet"]
