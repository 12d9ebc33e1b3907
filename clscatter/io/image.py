"""Image I/O, error metrics and error heatmaps for clscatter.

Images are ``float32`` arrays of shape ``(H, W, 3)`` holding linear RGB radiance
(see the radiometric conventions in the scene format). Row 0 is the top row of the
picture and column 0 its left column, in memory and in every file format.

File formats (chosen by the file name's suffix, case-insensitive)
------------------------------------------------------------------
``.exr``
    OpenEXR, written as three 32-bit float channels R, G, B (ZIP compression, scanline).
    Reading accepts half or float R, G, B channels (an alpha channel is ignored) or a
    single luminance channel ``Y`` (copied to all three channels). Lossless for float32.
``.npy``
    NumPy array, written as float32 ``(H, W, 3)``. Reading accepts ``(H, W)``,
    ``(H, W, 1)``, ``(H, W, 3)`` and ``(H, W, 4)`` of any real dtype. Lossless.
``.pfm``
    Portable float map, read and written by this module. Written as a colour map:
    ``PF\\n<W> <H>\\n-1.0\\n`` followed by little-endian float32 RGB triples, rows stored
    **bottom to top** (the PFM convention), so the file's first stored row is the
    image's last row. Reading accepts ``PF`` (colour) and ``Pf`` (grey) maps in either
    byte order (negative scale = little-endian, positive = big-endian); the magnitude
    of the scale is ignored. Lossless for float32.
``.png``
    For looking at, **lossy**: 8-bit sRGB produced by :func:`tonemap` (multiply by
    ``2**exposure``, clamp to [0, 1], exact piecewise sRGB OETF, round to the nearest of
    256 levels). Values above 1 (after exposure) and below 0 are clamped and lost;
    elsewhere the error is at most half an 8-bit step in sRGB. Reading a PNG inverts
    the sRGB curve (assuming exposure 0), so a PNG read back gives linear values in
    [0, 1]. 8- and 16-bit, grey, grey+alpha, RGB and RGBA PNGs are read (grey is copied
    to three channels, alpha is dropped).

Writers write what they are given, NaN and Inf included (the PNG tone mapper maps NaN
and -Inf to black and +Inf to white); callers that want clean data use :func:`sanitize`.
Writes are atomic: the data goes to a temporary file in the destination folder that is
then renamed over the destination with :func:`os.replace`, so a failed write leaves
no partial file behind. Unreadable or unwritable files and unsupported formats raise
:class:`~clscatter.errors.ImageError` with a one-line message naming the file.

Error metrics
-------------
All metrics take a test image ``a`` and a reference ``b`` of the same shape (a shape
mismatch raises ImageError naming both shapes), compute in float64 on linear values,
and average over all pixels **and** channels. With ``d = a - b`` and ``N`` the number
of values:

* ``rmse(a, b)      = sqrt(sum(d**2) / N)``
* ``relmse(a, b)    = sum(d**2 / (b**2 + f)) / N`` with the floor
  ``f = 0.01 * mean(|b|)**2`` by default (the mean over all pixels and channels of the
  reference; ``mean(|b|) = mean(b)`` for radiance, which is never negative): the relative
  MSE of the Monte Carlo rendering / denoising literature (Rousselle et al. 2011,
  Bitterli et al. 2016, Gharbi et al. 2019 use this form, up to a constant factor). It
  weights errors relative to the reference's brightness so that dark and bright regions
  count alike; the floor keeps near-black reference pixels (below a tenth of the mean)
  from dominating. Because the floor scales with the reference, relMSE does not depend
  on the units: ``relmse(k a, k b) == relmse(a, b)`` for any ``k > 0``, so a bound means
  the same on a dim image as on a bright one (a uniform error of ``x`` gives about
  ``x**2`` where the reference is well above a tenth of its mean, e.g. 4e-4 for 2 %).
  An explicit ``eps`` replaces the floor by that absolute value. The old default,
  ``eps = 1e-2`` (kept as ``RELMSE_EPS``), assumed radiance of order one: on an image of
  uniform radiance 0.003 a bound of 1e-4 admitted a 33 % error. Against a black
  reference (all zeros) relMSE is ``inf``, or 0 if the test image is black too.
* ``mean_ratio(a, b) = mean(a) / mean(b)``: the bias of the whole image (1 = none); not
  part of :func:`compare`.
* ``psnr(a, b)      = 10 * log10(peak**2 / mse)`` dB with ``peak = max(b)``;
  ``inf`` when the images are identical.
* ``ssim(a, b)``: mean SSIM from scikit-image's ``structural_similarity`` on the
  linear RGB channels (``channel_axis=-1``, SSIM averaged over channels), with
  ``data_range = max(b) - min(b)`` (1.0 if the reference is constant), the default
  uniform window of 7 x 7 pixels, shrunk to the largest odd size <= the image's
  smaller side for small images (and one global window for images under 3 pixels).
* ``max_error(a, b) = max(|d|)``.

:func:`compare` returns all five as a dict of floats; :func:`clscatter.io.stats.json_safe` turns the
non-finite ones into the strings ``"inf"``, ``"-inf"`` and ``"nan"`` for JSON.
:func:`check_comparable` refuses a pair of files of which one is linear (EXR, NPY, PFM)
and the other tone-mapped (PNG): ``clscatter diff`` compares only like with like.
"""
from __future__ import annotations

import math
import os
import re
import secrets
from pathlib import Path
from typing import Callable, Union

import numpy as np

from ..errors import ImageError

PathLike = Union[str, "os.PathLike[str]"]

SUPPORTED_SUFFIXES = (".exr", ".npy", ".pfm", ".png")

#: Formats that store linear radiance as it was rendered (lossless float32).
LINEAR_SUFFIXES = (".exr", ".npy", ".pfm")
#: Formats that store a tone-mapped picture (exposure, clamping to [0, 1], 8-bit sRGB).
TONE_MAPPED_SUFFIXES = (".png",)

#: :func:`relmse`'s default floor relative to the reference: ``f = RELMSE_FLOOR * mean(|b|)**2``.
RELMSE_FLOOR = 1e-2

#: The absolute ``eps`` relMSE used before its floor was scaled to the reference (kept for
#: callers that reproduce old records: ``relmse(a, b, eps=RELMSE_EPS)``).
RELMSE_EPS = 1e-2

#: Matplotlib colormap used by :func:`heatmap`.
HEATMAP_CMAP = "inferno"

#: Percentile of the per-pixel error that maps to the top of the heatmap's colormap.
HEATMAP_PERCENTILE = 99.0

METRIC_KEYS = ("rmse", "relmse", "psnr", "ssim", "max_error")


# --------------------------------------------------------------------------- helpers


def _one_line(text: object) -> str:
    """Collapse any whitespace (newlines included) in ``text`` to single spaces."""
    return " ".join(str(text).split())


def _err(path: PathLike, message: object) -> ImageError:
    return ImageError(_one_line(f"{os.fspath(path)}: {message}"))


def _reason(exc: BaseException) -> str:
    if isinstance(exc, OSError) and exc.strerror:
        return exc.strerror
    return str(exc) or type(exc).__name__


def _suffix(path: PathLike) -> str:
    suffix = Path(os.fspath(path)).suffix.lower()
    if suffix not in SUPPORTED_SUFFIXES:
        shown = f"'{suffix}'" if suffix else "no suffix"
        raise _err(
            path,
            f"unsupported image format ({shown}); supported suffixes: "
            + ", ".join(SUPPORTED_SUFFIXES),
        )
    return suffix


def _to_rgb(arr: np.ndarray, path: PathLike) -> np.ndarray:
    """Grey -> 3 channels, drop alpha; returns a C-contiguous float32 (H, W, 3) array."""
    arr = np.asarray(arr)
    if arr.dtype.kind not in "biuf":
        raise _err(path, f"unsupported pixel type {arr.dtype}")
    if arr.ndim == 2:
        arr = arr[:, :, None]
    if arr.ndim != 3 or arr.shape[2] not in (1, 2, 3, 4):
        raise _err(path, f"expected an H x W x 3 image, got an array of shape {arr.shape}")
    if arr.shape[2] in (1, 2):  # grey, grey + alpha
        arr = np.repeat(arr[:, :, :1], 3, axis=2)
    elif arr.shape[2] == 4:  # RGBA
        arr = arr[:, :, :3]
    return np.ascontiguousarray(arr, dtype=np.float32)


# ------------------------------------------------------------------------ tone curve


def srgb_oetf(linear: np.ndarray) -> np.ndarray:
    """Exact piecewise sRGB encoding of linear values in [0, 1] (IEC 61966-2-1)."""
    x = np.asarray(linear, dtype=np.float64)
    return np.where(
        x <= 0.0031308, 12.92 * x, 1.055 * np.power(np.maximum(x, 0.0031308), 1.0 / 2.4) - 0.055
    )


def srgb_eotf(encoded: np.ndarray) -> np.ndarray:
    """Inverse of :func:`srgb_oetf`: sRGB-encoded values in [0, 1] to linear."""
    v = np.asarray(encoded, dtype=np.float64)
    return np.where(
        v <= 0.04045, v / 12.92, np.power((np.maximum(v, 0.04045) + 0.055) / 1.055, 2.4)
    )


def tonemap(img: np.ndarray, exposure: float = 0.0) -> np.ndarray:
    """Tone-map linear radiance to 8-bit sRGB, ``uint8`` of the same shape.

    ``round(255 * oetf(clamp(img * 2**exposure, 0, 1)))`` with the exact sRGB curve
    (halves round up). NaN and -Inf map to 0, +Inf to 255.
    """
    e = float(exposure)
    if not math.isfinite(e):
        raise ImageError(f"exposure must be a finite number of stops (got {exposure!r})")
    # exp2 of a clipped exponent: any finite exposure works (2**1e6 would overflow a float);
    # beyond +-2000 stops every finite value is already 0 or saturated
    with np.errstate(over="ignore", invalid="ignore"):
        x = np.asarray(img, dtype=np.float64) * np.exp2(min(max(e, -2000.0), 2000.0))
    x = np.nan_to_num(x, nan=0.0, posinf=1.0, neginf=0.0)
    x = np.clip(x, 0.0, 1.0)
    return np.floor(srgb_oetf(x) * 255.0 + 0.5).astype(np.uint8)


def sanitize(img: np.ndarray) -> tuple[np.ndarray, int]:
    """Return ``(copy of img with NaN/Inf replaced by 0, number of values replaced)``."""
    arr = np.array(img, copy=True)
    if arr.dtype.kind != "f":
        return arr, 0
    bad = ~np.isfinite(arr)
    n_bad = int(np.count_nonzero(bad))
    if n_bad:
        arr[bad] = 0
    return arr, n_bad


def is_tone_mapped(path: PathLike) -> bool:
    """True for a file format that stores a tone-mapped picture (``.png``: exposure,
    clamping and 8-bit sRGB), False for one that stores linear radiance (``.exr``,
    ``.npy``, ``.pfm``). Reading a PNG inverts only the sRGB curve, so its values are not
    comparable with a linear image's (radiance above 1 was clamped, the exposure is
    unknown). Unsupported suffixes raise ImageError."""
    return _suffix(path) in TONE_MAPPED_SUFFIXES


def check_comparable(a_path: PathLike, b_path: PathLike) -> None:
    """Raise ImageError (one line naming both files) when one of the two files is linear
    and the other tone-mapped: metrics between them would mean nothing."""
    a_tm, b_tm = is_tone_mapped(a_path), is_tone_mapped(b_path)
    if a_tm == b_tm:
        return

    def kind(tone_mapped: bool) -> str:
        return "tone-mapped (PNG: clamped 8-bit sRGB)" if tone_mapped else "linear"

    raise ImageError(
        f"{os.fspath(a_path)} is {kind(a_tm)} but {os.fspath(b_path)} is {kind(b_tm)}: "
        "comparing a linear image with a tone-mapped one gives metrics that mean nothing; "
        "compare two linear images (.exr, .npy, .pfm) or two PNGs"
    )


# ----------------------------------------------------------------------------- PFM


_PFM_HEADER = re.compile(rb"(P[Ff])\s+(\d+)\s+(\d+)\s+([-+0-9.eE]+)\s")


def _parse_pfm(data: bytes, path: PathLike) -> np.ndarray:
    """Decode PFM bytes to a float32 ``(H, W, C)`` array with row 0 at the top."""
    # Header: type, width, height and scale separated by whitespace (normally
    # "PF\nW H\nscale\n"); exactly one whitespace byte follows the scale.
    m = _PFM_HEADER.match(data)
    if m is None:
        raise _err(path, "not a PFM file (expected a 'PF' or 'Pf' header)")
    channels = 3 if m.group(1) == b"PF" else 1
    width, height = int(m.group(2)), int(m.group(3))
    try:
        scale = float(m.group(4))
    except ValueError:
        raise _err(path, "bad PFM header (unreadable scale)") from None
    if width <= 0 or height <= 0 or scale == 0.0 or not math.isfinite(scale):
        raise _err(path, f"bad PFM header (width {width}, height {height}, scale {scale})")
    count = width * height * channels
    raster = data[m.end():]
    if len(raster) < 4 * count:
        raise _err(
            path,
            f"truncated PFM data ({len(raster)} bytes, {4 * count} expected for "
            f"{width} x {height} x {channels})",
        )
    dtype = np.dtype("<f4") if scale < 0 else np.dtype(">f4")
    arr = np.frombuffer(raster, dtype=dtype, count=count).reshape(height, width, channels)
    return arr[::-1].astype(np.float32)  # rows are stored bottom to top


def _pfm_bytes(img: np.ndarray) -> bytes:
    h, w, _ = img.shape
    header = f"PF\n{w} {h}\n-1.0\n".encode("ascii")
    return header + np.ascontiguousarray(img[::-1], dtype="<f4").tobytes()


# ---------------------------------------------------------------------------- read


def _check_magic(path: PathLike, magic: bytes, what: str) -> None:
    with open(path, "rb") as f:
        head = f.read(len(magic))
    if head != magic:
        raise _err(path, f"not {what} file (bad signature)")


_EXR_MAGIC = bytes([0x76, 0x2F, 0x31, 0x01])


def _read_exr(path: PathLike) -> np.ndarray:
    import OpenEXR

    _check_magic(path, _EXR_MAGIC, "an OpenEXR")  # so the C library prints nothing
    try:
        with OpenEXR.File(os.fspath(path), separate_channels=True) as f:
            chans = {name: ch.pixels for name, ch in f.channels().items()}
    except (RuntimeError, OSError, ValueError) as exc:
        raise _err(path, f"cannot read EXR: {_reason(exc)}") from None
    if all(c in chans for c in "RGB"):
        planes = [chans[c] for c in "RGB"]
    elif "Y" in chans:
        planes = [chans["Y"]] * 3
    else:
        raise _err(
            path,
            "EXR has no R, G, B (or Y) channels; channels: " + ", ".join(sorted(chans)),
        )
    try:
        return np.ascontiguousarray(np.stack(planes, axis=-1), dtype=np.float32)
    except ValueError as exc:  # e.g. subsampled channels of different sizes
        raise _err(path, f"cannot combine EXR channels: {exc}") from None


def _read_npy(path: PathLike) -> np.ndarray:
    _check_magic(path, b"\x93NUMPY", "a NumPy .npy")
    try:
        arr = np.load(os.fspath(path), allow_pickle=False)
    except (OSError, ValueError, EOFError) as exc:
        raise _err(path, f"cannot read NPY: {_reason(exc)}") from None
    if not isinstance(arr, np.ndarray):
        raise _err(path, "NPY file does not hold a single array")
    return _to_rgb(arr, path)


def _read_pfm(path: PathLike) -> np.ndarray:
    with open(path, "rb") as f:
        data = f.read()
    return _to_rgb(_parse_pfm(data, path), path)


def _read_png(path: PathLike) -> np.ndarray:
    import imageio.v3 as iio

    _check_magic(path, b"\x89PNG\r\n\x1a\n", "a PNG")
    try:
        arr = np.asarray(iio.imread(os.fspath(path), plugin="pillow", extension=".png"))
    except Exception as exc:  # imageio/Pillow raise many types for bad files
        raise _err(path, f"cannot read PNG: {exc}") from None
    # Pillow may hand 16-bit grey over as int32 (mode "I"); its values are 0..65535.
    is_16bit_int = arr.dtype.kind == "i" and arr.size and 0 <= arr.min() and arr.max() < 65536
    if arr.dtype == np.uint8:
        scale = 255.0
    elif arr.dtype == np.uint16 or is_16bit_int:
        scale = 65535.0
    elif arr.dtype == bool:
        scale = 1.0
    else:
        raise _err(path, f"unsupported PNG sample type {arr.dtype}")
    rgb = _to_rgb(arr, path)
    return srgb_eotf(rgb.astype(np.float64) / scale).astype(np.float32)


_READERS: dict[str, Callable[[PathLike], np.ndarray]] = {
    ".exr": _read_exr,
    ".npy": _read_npy,
    ".pfm": _read_pfm,
    ".png": _read_png,
}


def read_image(path: PathLike) -> np.ndarray:
    """Read an image file as linear float32 ``(H, W, 3)`` (format from the suffix)."""
    suffix = _suffix(path)
    if not os.path.exists(path):
        raise _err(path, "no such file")
    if os.path.isdir(path):
        raise _err(path, "is a folder, not an image file")
    try:
        img = _READERS[suffix](path)
    except ImageError:
        raise
    except OSError as exc:
        raise _err(path, f"cannot read image: {_reason(exc)}") from None
    if img.shape[0] == 0 or img.shape[1] == 0:
        raise _err(path, f"empty image ({img.shape[1]} x {img.shape[0]})")
    return img


# --------------------------------------------------------------------------- write


def _write_exr(tmp: str, img: np.ndarray) -> None:
    import OpenEXR

    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    with OpenEXR.File(header, {"RGB": np.ascontiguousarray(img, dtype=np.float32)}) as f:
        f.write(tmp)


def _write_npy(tmp: str, img: np.ndarray) -> None:
    with open(tmp, "wb") as f:
        np.save(f, np.ascontiguousarray(img, dtype=np.float32), allow_pickle=False)


def _write_pfm(tmp: str, img: np.ndarray) -> None:
    with open(tmp, "wb") as f:
        f.write(_pfm_bytes(img))


def _write_png(tmp: str, img: np.ndarray, exposure: float) -> None:
    import imageio.v3 as iio

    iio.imwrite(tmp, tonemap(img, exposure), plugin="pillow", extension=".png")


def _atomic_write(path: PathLike, writer: Callable[[str], None], what: str = "image") -> None:
    """Run ``writer(tmp)`` on a fresh temporary file next to ``path``, then rename it.

    On any failure the temporary file is removed and nothing is left at ``path``
    (an existing file there is untouched). OS and library errors become ImageError.
    """
    dest = os.fspath(path)
    folder, name = os.path.split(dest)
    suffix = Path(name).suffix
    tmp = os.path.join(folder, f".{name}.{secrets.token_hex(4)}.tmp{suffix}")
    try:
        # Create the temporary file with open() (mode 0666 minus umask), so the file
        # renamed into place gets ordinary permissions; the writer then overwrites it.
        with open(tmp, "xb"):
            pass
    except OSError as exc:
        raise _err(path, f"cannot write {what}: {_reason(exc)}") from None
    try:
        writer(tmp)
        os.replace(tmp, dest)
    except BaseException as exc:
        try:
            os.unlink(tmp)
        except OSError:
            pass
        if isinstance(exc, (OSError, RuntimeError, ValueError, TypeError)):
            raise _err(path, f"cannot write {what}: {_reason(exc)}") from None
        raise


def write_image(path: PathLike, img: np.ndarray, exposure: float = 0.0) -> None:
    """Write ``img`` (``(H, W, 3)``; grey ``(H, W)`` or ``(H, W, 1)`` is also accepted).

    The format follows the suffix of ``path`` (see the module docstring). ``exposure``
    (in stops) applies to ``.png`` only; the HDR formats store the values unchanged,
    NaN and Inf included. The file is written to a temporary name in the same folder
    and renamed into place, so a failed write leaves no partial file.
    """
    suffix = _suffix(path)
    arr = np.asarray(img)
    if not (arr.ndim == 2 or (arr.ndim == 3 and arr.shape[2] in (1, 3))):
        raise _err(path, f"cannot write an array of shape {arr.shape}; expected (H, W, 3)")
    rgb = _to_rgb(arr, path)
    if rgb.shape[0] == 0 or rgb.shape[1] == 0:
        raise _err(path, f"cannot write an empty image of shape {arr.shape}")
    if suffix == ".exr":
        _atomic_write(path, lambda tmp: _write_exr(tmp, rgb))
    elif suffix == ".npy":
        _atomic_write(path, lambda tmp: _write_npy(tmp, rgb))
    elif suffix == ".pfm":
        _atomic_write(path, lambda tmp: _write_pfm(tmp, rgb))
    else:
        _atomic_write(path, lambda tmp: _write_png(tmp, rgb, exposure))


# ------------------------------------------------------------------------- metrics


def _pair(a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    a = np.asarray(a, dtype=np.float64)
    b = np.asarray(b, dtype=np.float64)
    if a.shape != b.shape:
        raise ImageError(
            f"image shapes differ: test image {tuple(a.shape)} vs reference {tuple(b.shape)}"
        )
    if a.size == 0:
        raise ImageError(f"cannot compare empty images of shape {tuple(a.shape)}")
    return a, b


def rmse(a: np.ndarray, b: np.ndarray) -> float:
    """Root mean squared error ``sqrt(mean((a - b)**2))`` over pixels and channels."""
    a, b = _pair(a, b)
    return float(np.sqrt(np.mean((a - b) ** 2)))


def relmse(a: np.ndarray, b: np.ndarray, *, eps: float | None = None) -> float:
    """Relative MSE of test image ``a`` against reference ``b``.

    ``relmse = mean((a - b)**2 / (b**2 + f))``, the mean running over all pixels and
    channels, with the floor ``f = 0.01 * mean(|b|)**2`` (:data:`RELMSE_FLOOR` times the
    reference's mean squared, the mean over all its pixels and channels). This is the
    relative MSE used in the Monte Carlo rendering literature (Rousselle et al. 2011;
    Bitterli et al. 2016): each squared error is divided by the squared reference value,
    so a 10 % error counts the same in dark and bright regions, and the floor stops
    pixels darker than a tenth of the image's mean from dominating. The value does not
    depend on the units (scaling both images by ``k > 0`` leaves it unchanged); a uniform
    relative error ``x`` gives about ``x**2`` (4e-4 for 2 %) where the reference is
    bright against a tenth of its mean, less where it is dark.

    ``eps``, if given, is an absolute floor used instead (``RELMSE_EPS = 1e-2`` was the
    old default). A black reference (mean 0) gives ``inf``, or 0 if ``a`` equals it.
    """
    a, b = _pair(a, b)
    if eps is None:
        floor = RELMSE_FLOOR * float(np.mean(np.abs(b))) ** 2
        if floor == 0.0:  # black reference: any error is infinitely large relative to it
            return 0.0 if np.array_equal(a, b) else math.inf
        if not math.isfinite(floor):
            return math.nan
    else:
        floor = float(eps)
        if not floor > 0:
            raise ValueError(f"relmse eps must be positive, got {eps}")
    return float(np.mean((a - b) ** 2 / (b * b + floor)))


def mean_ratio(a: np.ndarray, b: np.ndarray) -> float:
    """``mean(a) / mean(b)`` over all pixels and channels: the test image's overall bias
    against reference ``b`` (1.0 = none). A reference of mean 0 gives 1.0 if ``a``'s mean
    is 0 too, else ``+-inf``."""
    a, b = _pair(a, b)
    ma, mb = float(np.mean(a)), float(np.mean(b))
    if mb == 0.0:
        return 1.0 if ma == 0.0 else math.copysign(math.inf, ma)
    return ma / mb


def psnr(a: np.ndarray, b: np.ndarray) -> float:
    """Peak signal-to-noise ratio in dB: ``10 log10(max(b)**2 / mse)``; ``inf`` if equal.

    A reference whose maximum is <= 0 has no meaningful peak: the result is then
    ``-inf`` (or ``inf`` if the images are equal).
    """
    a, b = _pair(a, b)
    mse = float(np.mean((a - b) ** 2))
    if mse == 0.0:
        return math.inf
    if math.isnan(mse):
        return math.nan
    peak = float(np.max(b))
    if not peak > 0.0:
        return math.nan if math.isnan(peak) else -math.inf
    return float(20.0 * math.log10(peak) - 10.0 * math.log10(mse))


def _ssim_global(a: np.ndarray, b: np.ndarray, data_range: float) -> float:
    """SSIM with one window covering the whole image (for images under 3 pixels)."""
    c1 = (0.01 * data_range) ** 2
    c2 = (0.03 * data_range) ** 2
    values = []
    pa = a.reshape(-1, a.shape[-1]) if a.ndim == 3 else a.reshape(-1, 1)
    pb = b.reshape(-1, b.shape[-1]) if b.ndim == 3 else b.reshape(-1, 1)
    for ca, cb in zip(pa.T, pb.T):
        ma, mb = ca.mean(), cb.mean()
        va, vb = ca.var(), cb.var()
        cov = np.mean((ca - ma) * (cb - mb))
        values.append(
            ((2 * ma * mb + c1) * (2 * cov + c2)) / ((ma * ma + mb * mb + c1) * (va + vb + c2))
        )
    return float(np.mean(values))


def ssim(a: np.ndarray, b: np.ndarray) -> float:
    """Mean structural similarity of ``a`` against reference ``b`` (1.0 = identical).

    scikit-image ``structural_similarity`` on the linear RGB channels
    (``channel_axis=-1``, averaged over channels; 2-D arrays are treated as one
    channel), ``data_range = max(b) - min(b)`` (1.0 for a constant reference), uniform
    7 x 7 window shrunk to the largest odd size <= the smaller image side; images with
    a side under 3 pixels use a single global window.
    """
    from skimage.metrics import structural_similarity

    a, b = _pair(a, b)
    if a.ndim not in (2, 3):
        raise ImageError(f"ssim needs an H x W or H x W x C image, got shape {a.shape}")
    data_range = float(np.max(b) - np.min(b))
    if not data_range > 0.0 or not math.isfinite(data_range):
        data_range = 1.0
    if np.array_equal(a, b):
        return 1.0
    side = min(a.shape[0], a.shape[1])
    if side < 3:
        return _ssim_global(a, b, data_range)
    win = min(7, side if side % 2 else side - 1)
    return float(
        structural_similarity(
            a,
            b,
            win_size=win,
            data_range=data_range,
            channel_axis=-1 if a.ndim == 3 else None,
        )
    )


def max_error(a: np.ndarray, b: np.ndarray) -> float:
    """Largest absolute difference ``max(|a - b|)`` over pixels and channels."""
    a, b = _pair(a, b)
    return float(np.max(np.abs(a - b)))


def compare(a: np.ndarray, b: np.ndarray) -> dict[str, float]:
    """All metrics of test image ``a`` against reference ``b``, as plain floats.

    Keys: ``rmse``, ``relmse``, ``psnr``, ``ssim``, ``max_error`` (``psnr`` is
    ``float('inf')`` for identical images; see :func:`clscatter.io.stats.json_safe`).
    """
    a, b = _pair(a, b)
    return {
        "rmse": rmse(a, b),
        "relmse": relmse(a, b),
        "psnr": psnr(a, b),
        "ssim": ssim(a, b),
        "max_error": max_error(a, b),
    }


# ------------------------------------------------------------------------- heatmap


def heatmap(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """False-colour image (``uint8 (H, W, 3)``) of the per-pixel error of ``a`` vs ``b``.

    The error of a pixel is its mean absolute difference over channels, divided by the
    99th percentile of the finite per-pixel errors (the maximum if that is 0) and
    clamped to [0, 1], then mapped through matplotlib's 'inferno' colormap: zero error
    is the colormap's first colour (black), errors at or above the percentile its last
    (pale yellow). Non-finite errors are shown at the top of the scale.
    """
    from matplotlib import colormaps

    a, b = _pair(a, b)
    if a.ndim not in (2, 3):
        raise ImageError(f"heatmap needs an H x W or H x W x C image, got shape {a.shape}")
    diff = np.abs(a - b)
    err = diff.mean(axis=-1) if diff.ndim == 3 else diff
    finite = np.isfinite(err)
    scale = 0.0
    if finite.any():
        vals = err[finite]
        scale = float(np.percentile(vals, HEATMAP_PERCENTILE))
        if not scale > 0.0:
            scale = float(vals.max())
    norm = np.zeros_like(err) if not scale > 0.0 else np.clip(err / scale, 0.0, 1.0)
    norm[~finite] = 1.0
    rgba = colormaps[HEATMAP_CMAP](norm, bytes=True)
    return np.ascontiguousarray(rgba[..., :3], dtype=np.uint8)


def write_heatmap(path: PathLike, a: np.ndarray, b: np.ndarray) -> None:
    """Write :func:`heatmap` of ``a`` vs ``b`` to ``path`` (``.png`` is the usual choice).

    For ``.png`` the 8-bit colours are stored as they are; other formats store them
    as linear values (decoded from sRGB), so they look the same when tone-mapped.
    """
    colours = heatmap(a, b)
    if _suffix(path) == ".png":
        import imageio.v3 as iio

        def writer(tmp: str) -> None:
            iio.imwrite(tmp, colours, plugin="pillow", extension=".png")

        _atomic_write(path, writer, "heatmap")
    else:
        write_image(path, srgb_eotf(colours / 255.0).astype(np.float32))


__all__ = [
    "SUPPORTED_SUFFIXES",
    "LINEAR_SUFFIXES",
    "TONE_MAPPED_SUFFIXES",
    "is_tone_mapped",
    "check_comparable",
    "RELMSE_EPS",
    "RELMSE_FLOOR",
    "METRIC_KEYS",
    "read_image",
    "write_image",
    "sanitize",
    "tonemap",
    "srgb_oetf",
    "srgb_eotf",
    "rmse",
    "relmse",
    "mean_ratio",
    "psnr",
    "ssim",
    "max_error",
    "compare",
    "heatmap",
    "write_heatmap",
]
