"""Scale-out on a Dask cluster: frames and camera-sample sets as tasks.

``clscatter render SCENE --workers N`` (a ``LocalCluster`` of N processes) or
``--cluster ADDRESS`` (a running scheduler) renders on ``dask.distributed``; nothing here
is imported without those options, and Dask is an optional extra (``pip install
clscatter[cluster]``).

Work units
    *Sample sets* of one image: the camera samples are cut into contiguous ranges; a task
    traces the view paths of its range and runs the passes of the plan on the segments it
    produced. A sample's paths and a segment's estimate depend only on their indices and
    the scene (deterministic seeds), so the partial images sum to the single-process image
    up to float summation order.
    *Progressive passes* of a caustic pass (methods with ``SPLIT_PASSES``: LSG): pass k of
    P traces its own lighting rays (seeded by k) with its own radius over the whole image,
    so each task does 1/P of the lighting-ray work; the driver averages them, exactly as one
    process averages its passes (a time budget becomes its pass count on a cluster).
    The driver adds all parts in unit order, whatever order they finish in.
    *Frames* of an animation (a list of ``--set`` overrides per frame): one task each.

Per worker, a :class:`ClscatterPlugin` opens the OpenCL device once and keeps a
:class:`~clscatter.pipeline.session.RenderSession` per scene, so the scene is sent once per worker
(``client.scatter(..., broadcast=True)``) and its BVH and device buffers are built once;
frames that follow on the same worker re-use them (the warm path).

Fault tolerance is Dask's: a worker that dies loses its in-flight tasks, the scheduler runs
them again elsewhere, and since a unit is deterministic the retried result is identical.
Statistics (``--stats``): ``cluster_workers``, ``cluster_tasks``, ``cluster_task_seconds``
(per task), ``cluster_bytes_in`` (scene payload x workers) and ``cluster_bytes_out``
(results returned).
"""
from __future__ import annotations

import hashlib
import json
import time
from typing import Any, Callable, Sequence

import numpy as np

from .io.stats import Stats, progress

PLUGIN_NAME = "clscatter"
CONNECT_TIMEOUT = "10s"      # how long joining a scheduler at an address may take


def _plugin_base():
    from distributed.diagnostics.plugin import WorkerPlugin
    return WorkerPlugin


def make_plugin(device: str | None = None):
    """A worker plugin that opens the OpenCL device once per worker and holds the
    worker's render sessions (one per scene)."""
    base = _plugin_base()

    class ClscatterPlugin(base):
        name = PLUGIN_NAME

        def __init__(self, device: str | None):
            self.device = device
            self.sessions: dict[str, Any] = {}

        def setup(self, worker) -> None:
            from .device import get_engine
            self.engine = get_engine(self.device)

        def teardown(self, worker) -> None:
            for s in self.sessions.values():
                s.close()
            self.sessions.clear()

    return ClscatterPlugin(device)


def _worker_session(payload: dict, method: str | None):
    """The calling worker's session for ``payload`` (made on first use)."""
    from distributed import get_worker

    from .pipeline.session import RenderSession
    plugin = get_worker().plugins[PLUGIN_NAME]
    key = payload["key"] + "|" + str(method)
    if key not in plugin.sessions:
        plugin.sessions[key] = RenderSession.from_data(
            payload["data"], payload["base_dir"], payload["source"], payload["overrides"],
            method=method, engine=plugin.engine, keep_hits=False)
    return plugin.sessions[key]


def _render_unit(payload: dict, method: str | None, unit: dict) -> dict:
    """Task: one unit (:func:`plan_units`): camera samples [lo, hi) of the passes that are
    not split by pass, or one progressive pass of a split pass over the whole image."""
    t = time.perf_counter()
    session = _worker_session(payload, method)
    res = session.render(show_progress=False, samples=unit.get("samples"), only=unit["only"],
                         pass_params={int(k): v for k, v in unit.get("params", {}).items()})
    surface = res.surface
    if unit.get("pass_unit"):        # the view paths' own shading comes with the sample sets
        surface = (surface - session.view_surface()) * unit["scale"]
    return {"surface": surface, "medium": res.medium * unit.get("scale", 1.0),
            "stats": res.stats, "seconds": time.perf_counter() - t}


def plan_units(passes, scene, total_samples: int, sample_units: int) -> tuple[list[dict], list[str]]:
    """Cut a render into tasks. A pass whose method can run its progressive passes apart
    (``SPLIT_PASSES``: LSG) becomes one task per progressive pass (its lighting rays are
    split across workers; each task's image is weighted 1/passes, so the sum is the mean of
    the passes, as in one process); a time budget becomes its pass count (a budget depends
    on the machine, a pass count does not). Every other pass runs on camera-sample sets;
    surface shading comes with the sample sets only."""
    from .methods import get_method
    split, rest, notes = [], [], []
    for k, p in enumerate(passes):
        cls = get_method(p.method)
        (split if cls.SPLIT_PASSES else rest).append(k)
    units: list[dict] = []
    n = max(1, min(int(sample_units), total_samples))
    bounds = [total_samples * i // n for i in range(n + 1)]
    units += [{"samples": (bounds[i], bounds[i + 1]), "only": rest} for i in range(n)]
    for k in split:
        table = passes[k].table(scene)
        count = int(table.get("passes", 1))
        if float(table.get("time_budget", 0.0)) > 0:
            notes.append(f"{passes[k].method}: time budget {table['time_budget']} s replaced by "
                         f"{count} passes on the cluster (deterministic)")
        units += [{"only": [k], "pass_unit": True, "scale": 1.0 / count,
                   "params": {str(k): {"first_pass": i, "passes": 1, "time_budget": 0.0}}}
                  for i in range(count)]
    return units, notes


def _render_frame(payload: dict, method: str | None, overrides: list[str]) -> dict:
    """Task: one whole frame (the worker's session moves to the frame's overrides)."""
    t = time.perf_counter()
    s = _worker_session(payload, method)
    s.set(overrides, replace=True)                       # frames are absolute, not cumulative
    res = s.render(show_progress=False)
    return {"image": res.image, "stats": res.stats, "seconds": time.perf_counter() - t}


def _lost_data_errors() -> tuple[type, ...]:
    from distributed.client import FutureCancelledError
    return (FutureCancelledError,)


def scene_payload(spec: str, overrides: Sequence[str] = ()) -> dict:
    """What a worker needs to rebuild the scene: raw data, base folder, overrides."""
    from .scene.loader import scene_source
    data, base_dir = scene_source(spec)
    blob = json.dumps([data, str(base_dir), str(spec), list(overrides)], sort_keys=True,
                      default=str)
    return {"key": hashlib.sha256(blob.encode()).hexdigest()[:20], "data": data,
            "base_dir": str(base_dir), "source": str(spec), "overrides": list(overrides),
            "bytes": len(blob)}


class Cluster:
    """A Dask client for clscatter: ``Cluster(workers=2)`` starts a LocalCluster of worker
    processes, ``Cluster(address="tcp://host:8786")`` joins a running scheduler. Use as a
    context manager; the plugin is registered on every worker."""

    def __init__(self, workers: int | None = None, address: str | None = None,
                 device: str | None = None):
        from distributed import Client, LocalCluster

        from .errors import ClscatterError
        self._local = None
        if address:
            try:
                self.client = Client(address, timeout=CONNECT_TIMEOUT)
            except ValueError as e:      # malformed: an unknown scheme, no port
                raise ClscatterError(f"--cluster {address}: not a scheduler address "
                                     f"({e})") from None
            except OSError as e:
                raise ClscatterError(f"--cluster {address}: cannot reach the scheduler ({e})") from None
        else:
            n = int(workers or 2)
            self._local = LocalCluster(n_workers=n, threads_per_worker=1, processes=True,
                                       dashboard_address=None, silence_logs=40)
            self.client = Client(self._local)
        self.client.register_plugin(make_plugin(device), name=PLUGIN_NAME)

    def workers(self) -> int:
        return len(self.client.scheduler_info()["workers"])

    def close(self) -> None:
        self.client.close()
        if self._local is not None:
            self._local.close()

    def __enter__(self) -> "Cluster":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # ---- one image --------------------------------------------------------------------------
    def render(self, spec: str, overrides: Sequence[str] = (), method: str | None = None,
               units: int | None = None, show_progress: bool = True,
               stats: Stats | None = None, on_unit: Callable[[int, int], None] | None = None):
        """The image of ``spec``, rendered as ``units`` camera-sample sets (default: four
        per worker), summed in unit order. ``on_unit(done, total)`` is called after each unit
        arrives. Returns a :class:`~clscatter.pipeline.render.RenderResult`."""
        from distributed import as_completed

        from .pipeline.render import RenderResult, check
        from .scene.loader import load_scene

        stats = stats or Stats()
        scene = load_scene(spec, overrides)
        req = check(scene, method)                # bad input fails here, not on a worker
        cam = scene.camera
        total = cam.width * cam.height * cam.spp
        work, unit_notes = plan_units(req.passes, scene, total,
                                      units or 4 * max(1, self.workers()))
        n = len(work)
        payload = scene_payload(spec, overrides)
        parts: dict[int, dict] = {}
        scatters = 0
        with stats.stage("cluster_render"), progress(n, "tasks", show_progress) as bar:
            for attempt in range(3):
                # the scene goes to every worker once; if the workers holding it all died
                # (its tasks then fail with "lost dependencies"), send it again and re-run
                # the units still missing
                # one future (a list of one): a dict would be scattered value by value
                # under its own key names ("data", "source"...), which every render shares
                fut = self.client.scatter([payload], broadcast=True, hash=False)[0]
                scatters += 1
                futures = {self.client.submit(_render_unit, fut, method, work[k], pure=False,
                                              retries=2): k
                           for k in range(n) if k not in parts}
                for f in as_completed(futures, loop=self.client.loop):   # not the default client's
                    try:
                        parts[futures[f]] = f.result()
                        bar.update(1)
                        if on_unit is not None:
                            on_unit(len(parts), n)
                    except _lost_data_errors():
                        pass
                if len(parts) == n:
                    break
            else:
                from .errors import ClscatterError
                raise ClscatterError("the cluster lost the scene three times; "
                                     "are its workers dying?")
        with stats.stage("cluster_sum"):
            surface = np.zeros((cam.height, cam.width, 3), np.float64)
            medium = np.zeros_like(surface)
            for k in range(n):                     # fixed order: the same sum every run
                surface += parts[k]["surface"]
                medium += parts[k]["medium"]
        first = parts[0]["stats"]
        image = (surface + medium).astype(np.float32)
        out_bytes = sum(p["surface"].nbytes + p["medium"].nbytes for p in parts.values())
        stats.set(**{k: first[k] for k in ("method", "requested_method", "plan", "passes",
                                           "device") if k in first},
                  width=cam.width, height=cam.height, spp=cam.spp,
                  peak_bytes=max(int(p["stats"].get("peak_bytes", 0)) for p in parts.values()),
                  cluster_workers=self.workers(), cluster_tasks=n,
                  cluster_units={"sample_sets": sum(1 for w in work if not w.get("pass_unit")),
                                 "progressive_passes": sum(1 for w in work if w.get("pass_unit"))},
                  cluster_notes=unit_notes,
                  cluster_task_seconds=[round(parts[k]["seconds"], 4) for k in range(n)],
                  cluster_bytes_in=int(payload["bytes"]) * self.workers() * scatters,
                  cluster_bytes_out=int(out_bytes))
        return RenderResult(image, stats.to_dict(), surface.astype(np.float32),
                            medium.astype(np.float32))

    # ---- frames -----------------------------------------------------------------------------
    def frames(self, spec: str, frame_overrides: Sequence[Sequence[str]],
               overrides: Sequence[str] = (), method: str | None = None,
               show_progress: bool = True,
               on_frame: Callable[[int, np.ndarray, dict], None] | None = None) -> dict:
        """Render one task per frame; ``on_frame(i, image, stats)`` is called in frame order
        as soon as every earlier frame is done. Returns per-frame statistics."""
        from distributed import as_completed

        payload = scene_payload(spec, overrides)
        fut = self.client.scatter([payload], broadcast=True, hash=False)[0]   # see render
        futures = {self.client.submit(_render_frame, fut, method, list(fo), pure=False,
                                      retries=2): i for i, fo in enumerate(frame_overrides)}
        done: dict[int, dict] = {}
        next_out = 0
        per_frame = []
        with progress(len(futures), "frames", show_progress) as bar:
            for f in as_completed(futures, loop=self.client.loop):   # not the default client's
                done[futures[f]] = f.result()
                bar.update(1)
                while next_out in done:
                    r = done.pop(next_out)
                    if on_frame is not None:
                        on_frame(next_out, r["image"], r["stats"])
                    per_frame.append({"frame": next_out, "seconds": r["seconds"],
                                      "stages": r["stats"].get("stages", {}),
                                      "stages_run": r["stats"].get("stages_run", [])})
                    next_out += 1
        return {"frames": per_frame, "cluster_workers": self.workers(),
                "cluster_tasks": len(futures)}


