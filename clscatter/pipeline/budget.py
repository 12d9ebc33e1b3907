"""Cost estimates before a render allocates anything, and the refusal of what cannot fit.

Every render estimates, from the scene and the checked method parameters alone, the peak
working set (host + device bytes) and the amount of work of each stage: the view paths
(camera samples) and every planned pass (``Method.estimate``). The sum is compared with a
memory budget, the smaller of the device's global memory and the machine's physical
memory, or ``--max-memory``. A pass that splits its work into parts it sums (LSG's chunks
of lighting rays) is first fitted to the budget with smaller parts (:func:`fit_memory`,
with a note); a render still over budget is refused with one line that names the scene
key to lower and the estimate, before any buffer exists. Work above
:data:`LONG_WORK` is allowed but announced (the progress bars show the ETA; Ctrl-C stops
between kernel launches and writes nothing).

The estimates are deliberately simple upper-bound models (bytes per camera sample, per
segment, per photon), stated next to each number; ``clscatter check`` prints them.
"""
from __future__ import annotations

import re
from collections.abc import Iterable
from dataclasses import replace

from ..device.memory import memory_budget
from ..errors import ClscatterError
from ..methods import configure, get_method
from ..methods.base import Estimate, camera_samples
from ..transport.progressive import BUDGET_SLACK

__all__ = ["Estimate", "camera_samples", "memory_budget", "estimate", "view_path_estimate",
           "scene_estimate", "time_budget", "AUTO_TIME_BUDGET", "BUDGET_SLACK",
           "check_budget", "fit_memory", "peak_bytes", "human_bytes", "parse_bytes",
           "long_work_notes"]

# bytes per camera sample kept by the view-path stage on the device: surface + escaped
# (2 x float4), the diffuse hits a warm session keeps for re-shading (80 bytes, about one
# per sample), and the medium segments (~1 per sample plus specular branches, 64 bytes each,
# held up to three times while being appended, stored and sorted)
BYTES_PER_SAMPLE = 32 + 80
BYTES_PER_SAMPLE_MEDIUM = BYTES_PER_SAMPLE + 3 * 64 * 2
# elementary operations above which a render is announced as long (~a minute on a CPU)
LONG_WORK = 2e10
# elementary operations above which a render is refused before it starts: days on a CPU,
# hours on a GPU, and 10x the largest legitimate render the built-in methods plan (a 4K
# image at 64 spp, 32 steps per segment and light, two lights: ~7e10)
REFUSE_WORK = 1e12
# device bytes per scene triangle while a render runs: the transformed triangle (48), its
# vertex normals (48), material index (4), its share of the BVH nodes and tile-grid lists
# (the host's own copies are bounded by the loader, clscatter.scene.loader)
DEVICE_BYTES_PER_TRIANGLE = 128
#: ``auto``'s whole-render time budget in seconds when ``render.time_budget`` is 0: its
#: progressive caustic passes share what the fixed passes leave of it
AUTO_TIME_BUDGET = 10.0


def time_budget(scene, requested: str) -> tuple[float, str]:
    """The render's time budget in seconds (0: none) and where it comes from: the scene's
    ``render.time_budget`` (also ``--time-budget``; 0 turns it off), or where that is
    absent, for ``auto``, its default :data:`AUTO_TIME_BUDGET`."""
    if scene.render.time_budget is not None:
        return float(scene.render.time_budget), "render.time_budget"
    if requested == "auto":
        return AUTO_TIME_BUDGET, "auto's default"
    return 0.0, "none"


def view_path_estimate(scene) -> Estimate:
    """The view-path stage: per camera sample bytes (see :data:`BYTES_PER_SAMPLE`)."""
    n = camera_samples(scene)
    per = BYTES_PER_SAMPLE_MEDIUM if scene.has_medium() else BYTES_PER_SAMPLE
    key = "camera.spp" if scene.camera.spp > 64 else "camera.resolution"
    return Estimate("view_paths", key, float(n) * per, float(n) * (1 + scene.render.max_depth),
                    "ray casts")


def scene_estimate(scene) -> Estimate:
    """The prepared scene on the device: its triangles, normals and BVH."""
    tris = float(scene.triangle_count())
    return Estimate("scene", "objects", tris * DEVICE_BYTES_PER_TRIANGLE, tris * 20,
                    "BVH build steps")


def estimate(scene, passes, settings: dict) -> list[Estimate]:
    """Estimates of the view paths, the prepared scene and every pass of the plan
    (``settings``: checked parameters per method,
    :func:`clscatter.methods.configure_scene`). The first two stay alive for the whole
    render; the passes run one after another."""
    out = [view_path_estimate(scene), scene_estimate(scene)]
    for p in passes:
        cls = get_method(p.method)
        params = configure(p.method, p.table(scene))
        out += cls.estimate(scene, params)
    return out


def human_bytes(n: float) -> str:
    for unit in ("B", "KiB", "MiB", "GiB", "TiB", "PiB"):
        if abs(n) < 1024 or unit == "PiB":
            return f"{n:.3g} {unit}" if unit != "B" else f"{int(n)} B"
        n /= 1024
    return f"{n:.3g} PiB"


def parse_bytes(text: str) -> float:
    """``"4G"``, ``"512MiB"``, ``"1e9"`` -> bytes (binary multiples); ClscatterError if not."""
    m = re.fullmatch(r"\s*([0-9.eE+]+)\s*([kKmMgGtT]?)(i?[bB])?\s*", str(text))
    try:
        value = float(m.group(1)) if m else float("nan")
    except ValueError:
        value = float("nan")
    if not m or not value > 0 or value == float("inf"):
        raise ClscatterError(f"--max-memory: expected a size such as 4G or 512M (got {text!r})")
    return value * 1024 ** " KMGT".index(m.group(2).upper() or " ")


def peak_bytes(estimates: list[Estimate]) -> float:
    """The view paths and the prepared scene stay alive while the passes run one after
    another: peak = both + the largest pass (:func:`estimate`'s order)."""
    kept, passes = estimates[:2], estimates[2:]
    return sum(e.bytes for e in kept) + max((e.bytes for e in passes), default=0.0)


def fit_memory(scene, req, budget: float, source: str) -> list[str]:
    """Where the peak of ``req`` (a checked request: ``passes``, ``estimates``) exceeds
    ``budget``, give every pass whose estimate does not fit beside the view paths and the
    scene the parameters with which it does (``Method.fit_memory``: smaller parts of the
    same work, down to the least parts it has), and estimate again. Returns a note per
    pass that then fits; where one does not, :func:`check_budget` refuses the render with
    the estimate of its least parts."""
    if peak_bytes(req.estimates) <= budget:
        return []
    room = budget - sum(e.bytes for e in req.estimates[:2])
    notes = []
    changed = False
    for i, p in enumerate(req.passes):
        cls = get_method(p.method)
        params = configure(p.method, p.table(scene))
        if sum(e.bytes for e in cls.estimate(scene, params)) <= room:
            continue
        more = cls.fit_memory(scene, params, room)
        if not more:
            continue
        req.passes[i] = replace(p, params={**p.params, **more})
        after = cls.estimate(scene, configure(p.method, req.passes[i].table(scene)))
        changed = True
        if sum(e.bytes for e in after) <= room:
            notes.append(f"{p.method}: " + ", ".join(
                f"render.{p.method}.{k} = {human_bytes(v) if k.endswith('bytes') else v}"
                for k, v in more.items())
                + f" to fit the {human_bytes(budget)} allowed ({source}): the same work in "
                "smaller parts")
    if changed:
        req.estimates = estimate(scene, req.passes, {})
    return notes


def check_budget(estimates: list[Estimate], budget: float, source: str) -> None:
    """Refuse (ClscatterError, one line) when the peak exceeds ``budget``, or a stage's work
    exceeds :data:`REFUSE_WORK`; the message names the key to lower and the estimate: the
    largest of the view paths and the scene where they alone exceed the budget (no pass
    setting would help), else the largest estimate."""
    peak = peak_bytes(estimates)
    if peak > budget:
        kept = estimates[:2]
        alone = sum(e.bytes for e in kept) > budget
        worst = max(kept if alone else estimates, key=lambda e: e.bytes)
        raise ClscatterError(
            f"{worst.key}: this render needs about {human_bytes(peak)} ({worst.stage}: "
            f"{human_bytes(worst.bytes)}), more than the {human_bytes(budget)} allowed "
            f"({source}); lower {worst.key}")
    for e in estimates:
        if e.work > REFUSE_WORK:
            raise ClscatterError(
                f"{e.work_by}: the {e.stage} stage would take about {e.work:.2g} {e.unit}, "
                f"far beyond what a render can do in reasonable time (at most "
                f"{REFUSE_WORK:.0e}); lower {e.work_by}")


def long_work_notes(estimates: list[Estimate], fitted: Iterable[str] = ()) -> list[str]:
    """One line per stage whose work exceeds :data:`LONG_WORK`, except the ``fitted``
    stages: methods whose passes a deadline sizes (their estimate is of the unshrunk
    work)."""
    fitted = set(fitted)
    return [f"{e.stage}: about {e.work:.2g} {e.unit} ({e.work_by}); this will take a while "
            "(Ctrl-C stops cleanly)" for e in estimates
            if e.work > LONG_WORK and e.stage not in fitted]
