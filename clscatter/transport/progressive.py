"""Progressive passes under a time budget and an error target, and the error estimate.

A method that refines its image by independent passes (fresh lighting rays each pass, the
image being the mean of the passes) asks its :class:`Progression` whether to run another
pass and hands it each pass's own image. The progression

* stops when the next pass would end past the deadline (the mean pass time so far
  predicts it; at least one pass always runs), when ``max_passes`` have run, or when the
  error estimate has fallen to ``target_error``;
* sizes passes: :meth:`pass_seconds` is the time one pass should take so that
  ``planned`` passes fit before the deadline, from which a method scales its work per
  pass by the throughput it measured (a pilot, or the previous pass);
* estimates the error of the mean image from two independent halves of the passes (even
  and odd): with ``A``, ``B`` the means of the halves (``n_a``, ``n_b`` passes), the
  per-pixel variance of one pass is ``(A - B)^2 / (1/n_a + 1/n_b)`` in expectation, so the
  variance of the mean of all ``n`` passes is that over ``n``. :func:`relmse_estimate`
  turns the variance image into a relMSE against the whole render's image, with the floor
  of :func:`clscatter.io.image.relmse`.

Passes whose gather radius shrinks (each pass hands its radius ``r``) also give the
blur's bias: with a pass's expected image ``truth + c r^k`` (:data:`BIAS_EXPONENT` k),
the mean ``A1`` of the first ``m`` passes (``m`` the largest power of two up to half the
passes) and the mean ``A2`` of the rest differ by ``c (s1 - s2)`` in expectation (``s1``,
``s2`` their mean ``r^k``), so the mean image's bias is about ``(A1 - A2) s / (s1 - s2)``
with ``s`` the mean ``r^k`` of all passes; its square, less the noise of ``A1 - A2``,
adds to the variance. The bias is relative to a converged image (radius 0); a render run
in one pass has no halves and no estimate.
"""
from __future__ import annotations

import math
import time
from typing import Callable

import numpy as np

from ..io.image import RELMSE_FLOOR

#: a time budget counts as kept while the time taken stays within this factor of it
BUDGET_SLACK = 1.2


class Cancelled(Exception):
    """A render was stopped by its ``cancel`` callback (between stages, or between the
    passes of a progression)."""
#: passes before the error target may stop a progression (two of each half)
MIN_PASSES_FOR_TARGET = 4
#: a pass's blur bias is modelled as c r^BIAS_EXPONENT (r: its gather radius)
BIAS_EXPONENT = 1.0
#: standard deviations by which the first passes must differ from the later ones before
#: their difference counts as blur
BIAS_SIGNIFICANCE = 3.0


def relmse_estimate(variance: np.ndarray, image: np.ndarray) -> float:
    """The relMSE that per-pixel ``variance`` (H, W, 3) gives against ``image``:
    ``mean(variance / (image^2 + f))``, ``f = RELMSE_FLOOR * mean(|image|)^2``."""
    floor = RELMSE_FLOOR * float(np.mean(np.abs(image))) ** 2
    if floor <= 0.0 or not math.isfinite(floor):
        return 0.0 if not np.any(variance) else math.inf
    return float(np.mean(variance / (image.astype(np.float64) ** 2 + floor)))


class Progression:
    """When a method's progressive passes stop, how long each should take, and how noisy
    their mean is (see the module docstring).

    ``deadline``: a ``clock()`` time the passes should end by (None: no time limit);
    ``target_error``: stop once the estimate is at most this (0: no target); ``max_passes``:
    at most this many; ``planned``: how many passes the time is shared among;
    ``image_so_far()``: the render's image without this method's passes (the error is
    relative to the whole image)."""

    def __init__(self, deadline: float | None = None, target_error: float = 0.0,
                 max_passes: int = 1, planned: int = 1,
                 image_so_far: Callable[[], np.ndarray | None] | None = None,
                 clock: Callable[[], float] = time.perf_counter,
                 cancel: Callable[[], bool] | None = None):
        self.deadline = deadline
        #: whether ``deadline`` is the method's own ``time_budget`` (not the render's)
        self.own_deadline = False
        self.target_error = float(target_error)
        self.max_passes = max(1, int(max_passes))
        self.planned = max(1, int(planned))
        self.clock = clock
        self._cancel = cancel
        self._image_so_far = image_so_far
        self.started = clock()
        self.seconds: list[float] = []
        self._sums: list[np.ndarray | None] = [None, None]     # even, odd passes
        self._counts = [0, 0]
        self._blur: list[float] = []                           # r^k of each pass
        self._snapshots: dict[int, np.ndarray] = {}           # sum of passes 1..m, m = 2^j
        self.bias2: float = 0.0
        self.error: float | None = None
        self.stopped_by = ""

    @property
    def budgeted(self) -> bool:
        return self.deadline is not None

    def remaining(self) -> float:
        """Seconds left before the deadline (inf without one)."""
        return math.inf if self.deadline is None else self.deadline - self.clock()

    def pass_seconds(self) -> float:
        """The time one of the remaining planned passes should take (inf without a deadline)."""
        left = max(self.planned - len(self.seconds), 1)
        return max(self.remaining(), 0.0) / left

    def more(self, next_seconds: float | None = None) -> bool:
        """Whether another pass should run; records why not in ``stopped_by``. Under a
        deadline the next pass is expected to take ``next_seconds`` (a method that sizes its
        passes says so) or else the mean of the passes so far. Raises :class:`Cancelled`
        when the render's ``cancel()`` says so (a newer change on the page: stale work
        stops within a pass's time)."""
        if self._cancel is not None and self._cancel():
            raise Cancelled("render cancelled")
        done = len(self.seconds)
        if done == 0:
            return True
        if done >= self.max_passes:
            self.stopped_by = "passes"
            return False
        if (self.target_error > 0 and done >= MIN_PASSES_FOR_TARGET and self.error is not None
                and self.error <= self.target_error):
            self.stopped_by = "target_error"
            return False
        if self.deadline is not None:
            mean = sum(self.seconds) / done if next_seconds is None else next_seconds
            if self.clock() + mean > self.deadline:
                self.stopped_by = "time_budget"
                return False
        return True

    def overrun_note(self, method: str, unit: str, lower: str) -> str | None:
        """One line when the first pass alone ran past this pass's share of the budget by
        more than :data:`BUDGET_SLACK` (None otherwise): ``unit`` says what the smallest
        pass was, ``lower`` which keys shrink it. A share used up by the passes before
        this one is said as such."""
        if not self.budgeted or not self.seconds:
            return None
        allowed = self.deadline - self.started
        first = self.seconds[0]
        if first <= BUDGET_SLACK * max(allowed, 0.0):
            return None
        share = (f"of the {allowed:.3g} s this pass had" if allowed > 0 else
                 "with no time left for it (the passes before it used the budget)")
        return (f"{method}: the first pass alone took {first:.3g} s {share} ({unit} is the "
                f"smallest unit of work); lower {lower}")

    def add(self, image: np.ndarray | None, seconds: float, radius: float | None = None) -> None:
        """One pass's own image (its estimate alone, not the running mean; None: not
        tracked: it times the passes but stays out of the error estimate), its time and its
        gather radius (None: no blur). The tracked passes alternate between the halves."""
        self.seconds.append(float(seconds))
        if image is None:
            return
        half = len(self._blur) % 2
        img = np.asarray(image, np.float64)
        self._sums[half] = img.copy() if self._sums[half] is None else self._sums[half] + img
        self._counts[half] += 1
        self._blur.append(0.0 if radius is None else float(radius) ** BIAS_EXPONENT)
        n = len(self._blur)
        if n & (n - 1) == 0:                                   # a power of two: keep the sum
            self._snapshots[n] = self._total()
        self.error = self._estimate()

    def _total(self) -> np.ndarray:
        return self._sums[0] if self._sums[1] is None else self._sums[0] + self._sums[1]

    def mean(self) -> np.ndarray | None:
        """The mean of the passes' images so far."""
        if self._sums[0] is None:
            return None
        return self._total() / sum(self._counts)

    def variance(self) -> np.ndarray | None:
        """Per-pixel variance of :meth:`mean` estimated from the two halves (None before
        each half has a pass)."""
        na, nb = self._counts
        if na == 0 or nb == 0:
            return None
        diff = self._sums[0] / na - self._sums[1] / nb
        return diff * diff / ((1.0 / na + 1.0 / nb) * (na + nb))

    def bias_squared(self, var: np.ndarray) -> np.ndarray | None:
        """Per-pixel squared blur bias of :meth:`mean`, less the noise its estimate carries
        (so it may be negative in a pixel); None without shrinking radii, before 2 passes,
        or where the first and later passes do not differ by more than
        :data:`BIAS_SIGNIFICANCE` standard deviations of their noise, relative to the
        image (the extrapolation to radius 0 would only amplify noise)."""
        n = len(self._blur)
        m = 1 << ((n // 2).bit_length() - 1) if n >= 2 else 0
        if m == 0:
            return None
        blur = np.asarray(self._blur)
        s1, s2, s = blur[:m].mean(), blur[m:].mean(), blur.mean()
        if not s1 - s2 > 1e-6 * s1:
            return None
        first = self._snapshots[m]
        diff = first / m - (self._total() - first) / (n - m)
        noise = var * n * (1.0 / m + 1.0 / (n - m))            # variance of diff
        excess = diff * diff - noise
        weight = 1.0 / self._denominator()
        # a squared normal variable has variance 2 var^2: the excess's noise, summed
        spread = math.sqrt(2.0 * float(np.sum((weight * noise) ** 2)))
        if not float(np.sum(weight * excess)) > BIAS_SIGNIFICANCE * spread:
            return None
        return excess * (s / (s1 - s2)) ** 2

    def _image(self) -> np.ndarray:
        """The render's image with this progression's mean (what errors are relative to)."""
        base = self._image_so_far() if self._image_so_far is not None else None
        mean = self.mean()
        return mean if base is None else base + mean

    def _denominator(self) -> np.ndarray:
        """relMSE's per-pixel denominator for :meth:`_image` (:func:`relmse_estimate`)."""
        image = self._image()
        floor = RELMSE_FLOOR * float(np.mean(np.abs(image))) ** 2
        return image.astype(np.float64) ** 2 + max(floor, 1e-300)

    def _estimate(self) -> float | None:
        var = self.variance()
        if var is None:
            return None
        image = self._image()
        noise = relmse_estimate(var, image)
        bias = self.bias_squared(var)
        self.bias2 = max(relmse_estimate(bias, image), 0.0) if bias is not None else 0.0
        return noise + self.bias2
