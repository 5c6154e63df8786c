"""Bench runs on a Ray cluster: each (trial, configuration, seed) run is one Ray task.

- **Resources.** A run is a task of :data:`TASK_CPUS` CPU and ``task_memory_gb`` GiB of memory
  (default :data:`DEFAULT_TASK_MEMORY_GB`), and its numba kernels use that many threads (a
  hypothesis's likelihood does not depend on the thread count: the rows stay the same). Ray runs
  as many at once as the nodes' CPUs and memory allow. The driver keeps :data:`WINDOW_PER_CPU` tasks per cluster CPU submitted (a long sweep does
  not flood the scheduler) and collects them with ``ray.wait``.
- **Code.** The driver's checkout goes with the job as its working directory (``ray.init(runtime_env=
  {"working_dir": REPO})``: the packages, ``configs/`` and ``meshes/``; not :data:`NOT_SHIPPED` nor
  what ``.gitignore`` names, about 1.5 MB), so that every node runs the driver's version and finds
  the files the code reads beside it; the nodes need the dependencies installed
  (``pip install -e '.[ray]'`` on each).
- **Trials.** A worker reads the trial from its path when it sees the same trial there
  (:func:`app.bench.bundles.fingerprint`; a shared file system). Otherwise the task answers
  "missing", and the driver packs the trial once into a Ray object (:mod:`app.bench.bundles`) and
  sends the task again with it; the worker unpacks it once per machine, and after the trial's last
  run every node removes its copy.
- **Lazy trials** (``bench --seeds``): a trial not yet simulated is simulated by a task of its own
  just before its first run (the mesh file goes with it); the driver unpacks the result into its
  cache folder, so that a second bench reuses it as a local one would.
- **Results** come back as rows (the ``trial_path`` the driver's) and, with ``--out``, each run's
  output folder, unpacked by the driver under the same path as a local run would write.

Ray is imported here only, when a :class:`RayExecutor` is made (``pip install -e '.[ray]'``).
"""
from __future__ import annotations

import logging
import os
import socket
import tempfile
from collections import deque
from dataclasses import replace
from pathlib import Path

from app.bench import bundles
from app.bench.configs import REPO
from app.errors import ConfigError

TASK_CPUS = 1
DEFAULT_TASK_MEMORY_GB = 1.0   # a run of a 0.5 s or a 3 s trial peaks at 0.39 GB RSS (BENCHMARKS.md)
WINDOW_PER_CPU = 2
RAY_INSTALL = "pip install -e '.[ray]'"
NOT_SHIPPED = ["tests/", "docs/", "plans/", "recordings/", ".git/", ".venv/", "*.rrd"]

log = logging.getLogger(__name__)


def import_ray():
    """The ``ray`` module; ConfigError naming ``--executor`` and the install command without it."""
    try:
        import ray
    except ImportError:
        raise ConfigError("--executor", f"ray needs the Ray package, which is not installed; install it with "
                          f"{RAY_INSTALL}") from None
    return ray


# --------------------------------------------------------------------------- on the workers

def run_remote(task: dict, key: str, bundle: bytes | None = None) -> dict:
    """Run one task on a worker: ``{"row", "out"}`` (``out``: the run's output folder packed, with
    ``--out``), or ``{"missing": path, "node": host}`` when the worker does not see the trial of
    fingerprint ``key`` at its path and no ``bundle`` came with the task."""
    from app.bench.runs import run_one

    logging.basicConfig(level=logging.WARNING)
    trial = task["trial"]
    path = trial.path
    if bundles.fingerprint(path) != key:
        if bundle is None:
            return {"missing": path, "node": socket.gethostname()}
        path = str(bundles.shipped_trial(bundle, key))
    with tempfile.TemporaryDirectory(prefix="osteonav-run-") as tmp:
        out = tmp if task["out_dir"] else None
        row = run_one(task["config"], replace(trial, path=path), out, with_vsd=task["with_vsd"])
        files = bundles.pack(out) if out else None
    row["trial_path"] = trial.path   # not the shipped copy's
    return {"row": row, "out": files}


def forget_remote(key: str) -> None:
    """Remove a shipped trial from this machine's cache (its last run has finished)."""
    import shutil

    shutil.rmtree(bundles.node_cache() / key, ignore_errors=True)


def simulate_remote(simulation: dict, mesh: bytes) -> bytes:
    """Simulate a lazy trial on a worker (``simulation``: :class:`app.bench.trials.TrialSpec`'s) and
    return it packed. ``mesh`` is the mesh file's content: a worker that lacks the file at its path
    uses a copy, and the trial's ``simulation.yaml`` still names the driver's path."""
    import yaml

    from app.bench.trials import _simulate_task

    with tempfile.TemporaryDirectory(prefix="osteonav-sim-") as tmp:
        source = Path(simulation["mesh"])
        mesh_path = source
        if not (source.is_file() and source.read_bytes() == mesh):
            mesh_path = Path(tmp) / "mesh" / source.name
            mesh_path.parent.mkdir()
            mesh_path.write_bytes(mesh)
        out = Path(tmp) / "trial"
        _simulate_task({**simulation, "mesh": str(mesh_path), "out": str(out)})
        if mesh_path != source:
            info_path = out / "simulation.yaml"
            info = yaml.safe_load(info_path.read_text())
            info["mesh_source"] = str(source)
            info_path.write_text(yaml.safe_dump(info, sort_keys=False))
        return bundles.pack(out)


# --------------------------------------------------------------------------- on the driver

def runtime_env() -> dict:
    """The job's runtime environment: the checkout (module docstring) and a run's threads, numba's
    included, held to its :data:`TASK_CPUS` (Ray sets ``OMP_NUM_THREADS`` itself)."""
    return {"working_dir": str(REPO), "excludes": NOT_SHIPPED, "env_vars": {"NUMBA_NUM_THREADS": str(TASK_CPUS)}}


def _check_reachable(address: str | None, timeout_s: float = 5.0) -> None:
    """ConfigError naming ``--address`` when ``HOST:PORT`` (or ``ray://HOST:PORT``) takes no
    connection (``ray.init`` would retry for minutes); None and ``auto`` are ``ray.init``'s to find."""
    if address in (None, "auto"):
        return
    host, sep, port = address.removeprefix("ray://").rpartition(":")
    if not sep or not port.isdigit():
        raise ConfigError("--address", f"expected auto or HOST:PORT (the head's, e.g. 10.0.0.5:6379), got '{address}'")
    try:
        socket.create_connection((host, int(port)), timeout=timeout_s).close()
    except OSError as exc:
        raise ConfigError("--address", f"no Ray cluster answers at {address} ({exc}); start one there with "
                          "`ray start --head --port PORT`, or give its head's HOST:PORT") from None


class RayExecutor:
    """Bench runs as Ray tasks on the cluster at ``address`` (``auto``: the one started on this
    machine with ``ray start``; ``HOST:PORT``: its head; None: that one if there is one, else a
    Ray instance started here for this bench, ``ray.init``'s rule). A process already connected
    to Ray keeps its connection, and its ``runtime_env`` decides the code the workers import."""

    name = "ray"

    def __init__(self, address: str | None = None, task_memory_gb: float = DEFAULT_TASK_MEMORY_GB):
        self.ray = import_ray()
        if task_memory_gb <= 0:
            raise ConfigError("--task-memory", f"expected GiB > 0, got {task_memory_gb}")
        self.address, self.task_memory_gb = address, task_memory_gb
        self._started = False
        self._connected = False

    def _connect(self) -> None:
        """Join (or start) the Ray instance on first use, and define the remote functions."""
        if self._connected:
            return
        ray = self.ray
        if not ray.is_initialized():
            _check_reachable(self.address)
            kwargs = {"include_dashboard": False} if self.address is None else {}
            try:
                ray.init(address=self.address, log_to_driver=True,
                         runtime_env=runtime_env(), **kwargs)
            except ConnectionError as exc:
                raise ConfigError("--address", f"no Ray cluster at '{self.address}' ({exc}); start one with "
                                  "`ray start --head`, or give its head's HOST:PORT") from None
            self._started = True
        options = {"num_cpus": TASK_CPUS, "memory": int(self.task_memory_gb * 2**30)}
        self._run = ray.remote(**options)(run_remote)
        self._simulate = ray.remote(**options)(simulate_remote)
        self._forget = ray.remote(num_cpus=0)(forget_remote)
        self._connected = True

    def cluster(self) -> dict:
        """Nodes alive and their CPUs."""
        self._connect()
        nodes = [n for n in self.ray.nodes() if n.get("Alive")]
        return {"nodes": len(nodes), "cpus": int(sum(n["Resources"].get("CPU", 0) for n in nodes))}

    def _check_fits(self) -> None:
        """ConfigError naming ``--task-memory`` when no node has the CPU and memory a run asks for
        (Ray would wait for such a node forever)."""
        need = self.task_memory_gb * 2**30
        nodes = [n["Resources"] for n in self.ray.nodes() if n.get("Alive")]
        if not any(r.get("CPU", 0) >= TASK_CPUS and r.get("memory", 0) >= need for r in nodes):
            most = max((r.get("memory", 0) for r in nodes), default=0) / 2**30
            raise ConfigError("--task-memory", f"no node of the Ray cluster has {TASK_CPUS} CPU and "
                              f"{self.task_memory_gb:g} GiB free for a run (the most a node offers: {most:.1f} GiB); "
                              "give a smaller --task-memory or add nodes")

    def describe(self) -> str:
        c = self.cluster()
        return f"Ray: {c['nodes']} node(s), {c['cpus']} CPU(s), one task of {TASK_CPUS} CPU per run"

    def close(self) -> None:
        """Shut down the Ray instance this executor started (not a cluster it joined)."""
        if self._started:
            self.ray.shutdown()
        self._started = self._connected = False

    def run(self, tasks: list[dict], progress: bool = True, on_row=None) -> list[dict]:
        """Every task as a Ray task; rows in completion order (module docstring)."""
        from tqdm import tqdm

        self._connect()
        self._check_fits()
        sweep = _Sweep(self, tasks)
        rows = []
        with tqdm(total=len(tasks), desc="bench", unit="run", disable=not progress, dynamic_ncols=True) as bar:
            try:
                for row in sweep.rows():
                    rows.append(row)
                    if on_row:
                        on_row(rows)
                    bar.set_postfix_str(f"{row['config']} on {row['trial']}")
                    bar.update(1)
                sweep.wait_cleanups()
            finally:
                sweep.cancel()
        return rows


class _Sweep:
    """The driver's side of one bench: trials in order, their runs submitted within the window."""

    def __init__(self, executor: RayExecutor, tasks: list[dict]):
        self.ex, self.ray = executor, executor.ray
        groups: dict[str, deque] = {}
        for task in tasks:   # trial-major, as app.bench.runs.bench_tasks makes them
            groups.setdefault(task["trial"].path, deque()).append(task)
        self.queue = deque(groups.values())
        self.left = {path: len(group) for path, group in groups.items()}
        self.keys: dict[str, str] = {}       # trial path -> fingerprint
        self.shipped: dict[str, object] = {}  # trial path -> ObjectRef of the packed trial
        self.inflight: dict = {}               # ObjectRef -> ("run", task) | ("sim", group)
        self.cleanups: list = []               # forget_remote tasks of shipped trials
        self.window = max(2, WINDOW_PER_CPU * executor.cluster()["cpus"] // TASK_CPUS)

    def rows(self):
        """Yield each finished run's row."""
        while self.queue or self.inflight:
            self._fill()
            [ref], _ = self.ray.wait(list(self.inflight), num_returns=1)
            kind, item = self.inflight.pop(ref)
            result = self._get(ref)
            if kind == "sim":
                self._simulated(item, result)
                continue
            if "missing" in result:
                log.info("%s does not see %s: shipping the trial", result["node"], result["missing"])
                path = item["trial"].path
                if path not in self.shipped:
                    self.shipped[path] = self.ray.put(bundles.pack(path))
                self._submit(item)
                continue
            if item["out_dir"] and result["out"] is not None:
                bundles.unpack(result["out"], item["out_dir"], replace=False)   # never removes what is there
            self._finished(item["trial"].path)
            yield {**result["row"], "trial_path": item["trial"].path}   # as given, as a local row has it

    def _get(self, ref):
        """The task's result; an osteonav error raised in the worker is raised here as itself
        (one line for the command), any other as Ray's error with the worker's traceback."""
        from app.errors import OsteonavError

        try:
            return self.ray.get(ref)
        except self.ray.exceptions.OutOfMemoryError as exc:
            first = str(exc).strip().splitlines()[0] if str(exc).strip() else "out of memory"
            raise ConfigError("--task-memory", f"Ray stopped a run for lack of memory on its node ({first}); give a "
                              f"larger --task-memory than {self.ex.task_memory_gb:g} GiB, so that fewer runs share "
                              "a node") from None
        except self.ray.exceptions.RayTaskError as exc:
            if isinstance(exc.cause, OsteonavError):
                raise exc.cause from None
            raise

    def cancel(self) -> None:
        """Cancel what is still running (after an error or an interruption)."""
        for ref in self.inflight:
            try:
                self.ray.cancel(ref)
            except Exception:  # noqa: BLE001 -- best effort: the task may have finished meanwhile
                pass
        self.inflight.clear()

    def _fill(self) -> None:
        while self.queue and len(self.inflight) < self.window:
            group = self.queue[0]
            trial = group[0]["trial"]
            if trial.simulation is not None:
                self.queue.popleft()
                mesh = Path(trial.simulation["mesh"]).read_bytes()
                self.inflight[self.ex._simulate.remote(trial.simulation, mesh)] = ("sim", group)
                continue
            task = group.popleft()
            if not group:
                self.queue.popleft()
            self._submit(task)

    def _submit(self, task: dict) -> None:
        trial = task["trial"]
        key = self.keys.get(trial.path)
        if key is None:
            key = self.keys[trial.path] = bundles.fingerprint(trial.path)
        payload = {**task, "trial": replace(trial, path=os.path.abspath(trial.path))}
        ref = self.ex._run.remote(payload, key, self.shipped.get(trial.path))
        self.inflight[ref] = ("run", task)

    def _simulated(self, group: deque, packed: bytes) -> None:
        """A lazy trial came back simulated: into the driver's cache, then its runs go first."""
        from app.trial.reader import open_trial

        trial = group[0]["trial"]
        bundles.unpack(packed, trial.path)
        trial.simulation = None
        trial.frames = len(open_trial(trial.path))
        self.queue.appendleft(group)

    def _finished(self, path: str) -> None:
        self.left[path] -= 1
        if not self.left[path] and self.shipped.pop(path, None) is not None:
            self._forget_everywhere(self.keys[path])   # its last run: the object and the nodes' copies go

    def _forget_everywhere(self, key: str) -> None:
        from ray.util.scheduling_strategies import NodeAffinitySchedulingStrategy

        for node in self.ray.nodes():
            if node.get("Alive"):
                strategy = NodeAffinitySchedulingStrategy(node["NodeID"], soft=False)
                self.cleanups.append(self.ex._forget.options(scheduling_strategy=strategy).remote(key))

    def wait_cleanups(self, timeout_s: float = 60.0) -> None:
        """Wait (a while) for the shipped trials' copies to be removed from the nodes."""
        if self.cleanups:
            self.ray.wait(self.cleanups, num_returns=len(self.cleanups), timeout=timeout_s)
