"""Tests for clscatter.io.image: file formats, metrics, heatmaps and the diff command."""
from __future__ import annotations

import json
import math
import os
import struct

import imageio.v3 as iio
import numpy as np
import OpenEXR
import pytest
from matplotlib import colormaps

from clscatter.cli import diff_command
from clscatter.errors import ImageError
from clscatter.io import image as im

LOSSLESS = ("exr", "npy", "pfm")


def _random_image(h: int = 13, w: int = 17, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    # Spread over many magnitudes so mantissa and exponent bits are all exercised.
    return (rng.random((h, w, 3)) * 10.0 ** rng.integers(-6, 6, (h, w, 3))).astype(np.float32)


def _bits(a: np.ndarray) -> np.ndarray:
    return np.ascontiguousarray(a, dtype=np.float32).view(np.uint32)


def _gradient(h: int = 6, w: int = 4) -> np.ndarray:
    """Row r, column c, channel k holds 100 r + 10 c + k (exact in float32)."""
    r, c, k = np.meshgrid(np.arange(h), np.arange(w), np.arange(3), indexing="ij")
    return (100.0 * r + 10.0 * c + k).astype(np.float32)


def _assert_one_line(exc: pytest.ExceptionInfo) -> str:
    msg = str(exc.value)
    assert "\n" not in msg and "\r" not in msg, msg
    assert msg.strip() == msg and msg
    return msg


# ------------------------------------------------------------------ round trips


@pytest.mark.parametrize("fmt", LOSSLESS)
def test_lossless_round_trip_is_bitwise(tmp_path, fmt):
    img = _random_image()
    # Special values must survive too: signed zero, a denormal, huge values, inf, NaN.
    img[0, 0] = [-0.0, 1e-40, 3.0e38]
    img[1, 1] = [np.inf, -np.inf, np.nan]
    img[2, 2] = [-1.5, 0.1, 1.0 / 3.0]
    path = tmp_path / f"img.{fmt}"
    im.write_image(path, img)
    back = im.read_image(path)
    assert back.dtype == np.float32 and back.shape == img.shape
    np.testing.assert_array_equal(_bits(back), _bits(img))


@pytest.mark.parametrize("fmt", LOSSLESS + ("png",))
def test_round_trip_str_path_and_uppercase_suffix(tmp_path, fmt):
    img = np.full((3, 5, 3), 0.5, np.float32)
    path = str(tmp_path / f"IMG.{fmt.upper()}")
    im.write_image(path, img)
    back = im.read_image(path)
    assert back.shape == (3, 5, 3)
    assert np.max(np.abs(back - 0.5)) <= 0.003  # PNG: one 8-bit step near 0.5 is ~0.0042


def test_png_round_trip_within_one_8bit_step(tmp_path):
    rng = np.random.default_rng(1)
    img = rng.random((32, 24, 3)).astype(np.float32)
    img[0, :3] = [[0.0, 0.0, 0.0], [1.0, 1.0, 1.0], [0.0031308, 0.002, 0.5]]
    path = tmp_path / "img.png"
    im.write_image(path, img)
    back = im.read_image(path)
    assert back.dtype == np.float32 and back.shape == img.shape
    assert back.min() >= 0.0 and back.max() <= 1.0
    # In the sRGB domain the error is at most half a step (rounding) ...
    err = np.abs(im.srgb_oetf(back) - im.srgb_oetf(img))
    assert err.max() <= 0.5 / 255 + 1e-6
    # ... so re-quantising gives exactly the stored 8-bit codes.
    np.testing.assert_array_equal(im.tonemap(back), im.tonemap(img))
    np.testing.assert_array_equal(iio.imread(path), im.tonemap(img))
    # Black and white survive exactly.
    np.testing.assert_array_equal(back[0, 0], [0, 0, 0])
    np.testing.assert_array_equal(back[0, 1], [1, 1, 1])


def test_png_is_clamped_and_uses_exposure(tmp_path):
    img = np.array([[[0.25, 2.0, -1.0]]], np.float32)
    path = tmp_path / "exp.png"
    im.write_image(path, img, exposure=1.0)
    # 0.25 * 2 = 0.5 -> sRGB 0.7353570 -> 187.52 -> 188; 4.0 clamps to 255; <0 to 0.
    np.testing.assert_array_equal(iio.imread(path)[0, 0], [188, 255, 0])
    back = im.read_image(path)
    assert back[0, 0, 1] == 1.0 and back[0, 0, 2] == 0.0  # clamped values are lost


def test_srgb_curve_and_tonemap_known_values():
    # Exact piecewise sRGB: linear segment below 0.0031308, power segment above.
    np.testing.assert_allclose(im.srgb_oetf(np.array([0.001])), [0.01292], rtol=1e-12)
    np.testing.assert_allclose(im.srgb_oetf(np.array([0.18])), [0.4613561295], rtol=1e-9)
    np.testing.assert_allclose(im.srgb_oetf(np.array([1.0])), [1.0], rtol=1e-12)
    x = np.linspace(0, 1, 1001)
    np.testing.assert_allclose(im.srgb_eotf(im.srgb_oetf(x)), x, atol=1e-12)
    tm = im.tonemap(np.array([[[np.nan, np.inf, -np.inf], [0.5, 1.0, 0.0]]]))
    assert tm.dtype == np.uint8 and tm.shape == (1, 2, 3)
    np.testing.assert_array_equal(tm[0], [[0, 255, 0], [188, 255, 0]])
    # exposure -1 halves: 1.0 -> 0.5 -> 188
    assert im.tonemap(np.ones((1, 1, 3)), exposure=-1.0)[0, 0, 0] == 188


# ----------------------------------------------------------------------- PFM


def test_pfm_orientation_round_trip(tmp_path):
    img = _gradient()
    path = tmp_path / "grad.pfm"
    im.write_image(path, img)
    back = im.read_image(path)
    np.testing.assert_array_equal(back, img)
    assert back[0, 0, 0] == 0.0 and back[5, 0, 0] == 500.0  # row 0 stays at the top
    assert back[0, 3, 2] == 32.0  # column 3, channel 2

    data = path.read_bytes()
    header = b"PF\n4 6\n-1.0\n"
    assert data.startswith(header)
    raster = np.frombuffer(data[len(header):], dtype="<f4")
    assert raster.size == 6 * 4 * 3
    # The first stored row is the image's bottom row (row 5), left to right, RGB.
    np.testing.assert_array_equal(raster[:6], [500, 501, 502, 510, 511, 512])
    # The last stored row is the image's top row.
    np.testing.assert_array_equal(raster[-3:], [30, 31, 32])


def test_pfm_parse_hand_made_little_endian(tmp_path):
    # 3 wide, 2 high. Stored bottom row first: bottom row = pixels 1..3, top = 4..6.
    bottom = [1.0, 1.5, 1.25, 2.0, 2.5, 2.25, 3.0, 3.5, 3.25]
    top = [4.0, 4.5, 4.25, 5.0, 5.5, 5.25, 6.0, 6.5, 6.25]
    data = b"PF\n3 2\n-1.0\n" + struct.pack("<18f", *(bottom + top))
    path = tmp_path / "hand.pfm"
    path.write_bytes(data)
    img = im.read_image(path)
    assert img.shape == (2, 3, 3)
    np.testing.assert_array_equal(img[0], np.reshape(top, (3, 3)))
    np.testing.assert_array_equal(img[1], np.reshape(bottom, (3, 3)))


def test_pfm_parse_hand_made_big_endian_and_grey(tmp_path):
    values = [1.0, 2.0, 3.0, 4.0, 5.0, 6.0]  # 2 wide, 3 high, grey, bottom row first
    path = tmp_path / "be.pfm"
    # Positive scale = big endian; the magnitude (here 2.5) is ignored.
    path.write_bytes(b"Pf\n2 3\n2.5\n" + struct.pack(">6f", *values))
    img = im.read_image(path)
    assert img.shape == (3, 2, 3)
    expected = np.array([[5.0, 6.0], [3.0, 4.0], [1.0, 2.0]])
    for k in range(3):  # grey copied to all channels
        np.testing.assert_array_equal(img[:, :, k], expected)
    # Reading the same bytes as little endian would give garbage, not these values.
    assert struct.unpack("<f", struct.pack(">f", 1.0))[0] != 1.0


def test_pfm_truncated_and_bad_header(tmp_path):
    path = tmp_path / "short.pfm"
    path.write_bytes(b"PF\n3 2\n-1.0\n" + struct.pack("<5f", *range(5)))
    with pytest.raises(ImageError) as exc:
        im.read_image(path)
    assert "short.pfm" in _assert_one_line(exc)
    path = tmp_path / "notpfm.pfm"
    path.write_bytes(b"P6\n3 2\n255\n" + bytes(18))
    with pytest.raises(ImageError) as exc:
        im.read_image(path)
    assert "notpfm.pfm" in _assert_one_line(exc)


# ------------------------------------------------------------ format variants


def test_read_half_rgba_exr(tmp_path):
    rng = np.random.default_rng(2)
    half = rng.random((5, 6, 4)).astype(np.float16)
    # (OpenEXR needs contiguous channel arrays; it ignores the strides of a view.)
    chans = {c: np.ascontiguousarray(half[:, :, i]) for i, c in enumerate("RGBA")}
    path = tmp_path / "half.exr"
    OpenEXR.File({}, chans).write(str(path))
    img = im.read_image(path)
    assert img.dtype == np.float32 and img.shape == (5, 6, 3)
    np.testing.assert_array_equal(img, half[:, :, :3].astype(np.float32))


def test_read_luminance_exr(tmp_path):
    y = np.arange(12, dtype=np.float32).reshape(3, 4)
    path = tmp_path / "y.exr"
    OpenEXR.File({}, {"Y": y}).write(str(path))
    img = im.read_image(path)
    np.testing.assert_array_equal(img, np.repeat(y[:, :, None], 3, axis=2))


def test_read_grey_and_rgba_png(tmp_path):
    grey = np.array([[0, 128, 255]], np.uint8)
    iio.imwrite(tmp_path / "g.png", grey)
    img = im.read_image(tmp_path / "g.png")
    assert img.shape == (1, 3, 3)
    expected = im.srgb_eotf(grey / 255.0)
    for k in range(3):
        np.testing.assert_allclose(img[:, :, k], expected, rtol=1e-6)
    assert img[0, 1, 0] == pytest.approx(0.2158605, abs=1e-6)  # sRGB 128/255

    rgba = np.zeros((2, 2, 4), np.uint8)
    rgba[..., 0] = 255
    rgba[..., 3] = 7  # alpha dropped, not premultiplied
    iio.imwrite(tmp_path / "a.png", rgba)
    img = im.read_image(tmp_path / "a.png")
    np.testing.assert_array_equal(img, np.broadcast_to([1.0, 0.0, 0.0], (2, 2, 3)))

    sixteen = np.array([[0, 65535]], np.uint16)  # 16-bit grey PNG
    iio.imwrite(tmp_path / "s.png", sixteen)
    np.testing.assert_array_equal(im.read_image(tmp_path / "s.png"), [[[0.0] * 3, [1.0] * 3]])


def test_read_npy_variants(tmp_path):
    grey = np.arange(6, dtype=np.float64).reshape(2, 3)
    np.save(tmp_path / "g.npy", grey)
    img = im.read_image(tmp_path / "g.npy")
    assert img.dtype == np.float32 and img.shape == (2, 3, 3)
    np.testing.assert_array_equal(img[:, :, 2], grey)
    rgba = np.arange(24, dtype=np.float32).reshape(2, 3, 4)
    np.save(tmp_path / "a.npy", rgba)
    np.testing.assert_array_equal(im.read_image(tmp_path / "a.npy"), rgba[:, :, :3])
    np.save(tmp_path / "bad.npy", np.zeros((2, 3, 5)))
    with pytest.raises(ImageError) as exc:
        im.read_image(tmp_path / "bad.npy")
    msg = _assert_one_line(exc)
    assert "bad.npy" in msg and "(2, 3, 5)" in msg


# --------------------------------------------------------- writing, sanitize


def test_write_is_atomic_on_failure(tmp_path, monkeypatch):
    path = tmp_path / "out.pfm"
    im.write_image(path, np.ones((2, 2, 3), np.float32))
    before = path.read_bytes()

    def broken_writer(tmp, img):
        with open(tmp, "wb") as f:
            f.write(b"PF\n2 2\n-1.0\n\x00\x00")  # half-written
        raise RuntimeError("disk on fire")

    monkeypatch.setattr(im, "_write_pfm", broken_writer)
    with pytest.raises(ImageError) as exc:
        im.write_image(path, np.zeros((2, 2, 3), np.float32))
    msg = _assert_one_line(exc)
    assert "out.pfm" in msg and "disk on fire" in msg
    assert path.read_bytes() == before  # old file untouched
    assert sorted(os.listdir(tmp_path)) == ["out.pfm"]  # no temporary left behind

    new = tmp_path / "new.pfm"
    with pytest.raises(ImageError):
        im.write_image(new, np.zeros((2, 2, 3), np.float32))
    assert not new.exists()
    assert sorted(os.listdir(tmp_path)) == ["out.pfm"]


def test_write_errors(tmp_path):
    with pytest.raises(ImageError) as exc:
        im.write_image(tmp_path / "missing_dir" / "x.exr", np.zeros((2, 2, 3)))
    assert "x.exr" in _assert_one_line(exc)
    with pytest.raises(ImageError) as exc:
        im.write_image(tmp_path / "x.npy", np.zeros((2, 2, 5)))
    assert "x.npy" in _assert_one_line(exc)
    with pytest.raises(ImageError) as exc:
        im.write_image(tmp_path / "x.jpg", np.zeros((2, 2, 3)))
    msg = _assert_one_line(exc)
    assert "x.jpg" in msg and all(s in msg for s in (".exr", ".npy", ".pfm", ".png"))
    assert os.listdir(tmp_path) == []


def test_write_grey_and_float64_input(tmp_path):
    grey = np.arange(6, dtype=np.float64).reshape(2, 3) / 8.0
    im.write_image(tmp_path / "g.npy", grey)
    back = np.load(tmp_path / "g.npy")
    assert back.dtype == np.float32 and back.shape == (2, 3, 3)
    np.testing.assert_array_equal(back[:, :, 1], grey)


def test_sanitize():
    img = np.array([[[1.0, np.nan, np.inf], [-np.inf, -2.0, 0.5]]], np.float32)
    clean, n_bad = im.sanitize(img)
    assert n_bad == 3
    np.testing.assert_array_equal(clean, [[[1.0, 0.0, 0.0], [0.0, -2.0, 0.5]]])
    assert clean.dtype == np.float32
    assert np.isnan(img[0, 0, 1])  # input untouched
    clean2, n2 = im.sanitize(clean)
    assert n2 == 0 and np.array_equal(clean2, clean)


# -------------------------------------------------------------------- metrics


def _smooth(h: int = 48, w: int = 40) -> np.ndarray:
    y, x = np.mgrid[0:h, 0:w] / 16.0
    base = 0.5 + 0.4 * np.sin(x) * np.cos(y)
    return np.stack([base, 0.8 * base, 1.2 * base], axis=-1)


def test_metrics_identical_images():
    img = _smooth().astype(np.float32)
    m = im.compare(img, img)
    assert set(m) == {"rmse", "relmse", "psnr", "ssim", "max_error"}
    assert all(type(v) is float for v in m.values())
    assert m["rmse"] == 0.0 and m["relmse"] == 0.0 and m["max_error"] == 0.0
    assert m["psnr"] == math.inf
    assert m["ssim"] == 1.0


def test_constant_offset():
    # Values on a 1/256 grid and an offset of 0.25 are exact in float32.
    rng = np.random.default_rng(3)
    b = (rng.integers(0, 256, (20, 30, 3)) / 256.0).astype(np.float32)
    a = b + np.float32(0.25)
    assert im.rmse(a, b) == 0.25
    assert im.max_error(a, b) == 0.25
    assert im.rmse(b, a) == 0.25


def test_relmse_hand_computation():
    b = np.array([[[0.0, 1.0, 2.0]]])
    a = np.array([[[0.1, 1.5, 1.0]]])
    # floor = 0.01 * mean(b)**2 = 0.01 (mean(b) = 1):
    # (0.1^2 / (0 + 0.01) + 0.5^2 / (1 + 0.01) + 1^2 / (4 + 0.01)) / 3
    expected = (1.0 + 0.25 / 1.01 + 1.0 / 4.01) / 3.0
    assert expected == pytest.approx(0.4989671037, abs=1e-9)
    assert im.relmse(a, b) == pytest.approx(expected, rel=1e-12)
    # explicit eps: (0.01/1 + 0.25/2 + 1/5) / 3
    assert im.relmse(a, b, eps=1.0) == pytest.approx(0.335 / 3.0, rel=1e-12)
    # relative: scaling both images by 10 with eps scaled by 100 gives the same value
    assert im.relmse(10 * a, 10 * b, eps=1.0) == pytest.approx(im.relmse(a, b), rel=1e-12)
    # asymmetric: the reference is the second argument
    assert im.relmse(b, a) != pytest.approx(im.relmse(a, b))


def test_relmse_floor_scales_with_the_reference():
    """The default floor is 0.01 * mean(b)**2, so the value does not depend on the units:
    a 34 % error on a dim image (mean 0.003) is as large as on a bright one, where the
    old absolute eps = 1e-2 made it 1e-4."""
    rng = np.random.default_rng(6)
    b = 0.5 + rng.random((12, 10, 3))
    a = b * (1.0 + 0.1 * rng.standard_normal(b.shape))
    for k in (1e-6, 3e-3, 1.0, 1e4):
        assert im.relmse(k * a, k * b) == pytest.approx(im.relmse(a, b), rel=1e-9)
    dim = np.full((8, 8, 3), 0.003)
    assert im.relmse(1.34 * dim, dim, eps=im.RELMSE_EPS) < 1.1e-4       # the old metric
    assert im.relmse(1.34 * dim, dim) == pytest.approx(0.34**2 / 1.01, rel=1e-9)
    assert im.relmse(1.02 * dim, dim) == pytest.approx(4e-4 / 1.01, rel=1e-9)
    # the floor is the mean over all pixels and channels, squared
    b2 = np.zeros((1, 4, 3))
    b2[0, 0] = 4.0                     # mean 1 -> floor 0.01
    a2 = b2.copy()
    a2[0, 3, 0] = 0.1                  # an error of 0.1 on a black pixel
    assert im.relmse(a2, b2) == pytest.approx(0.01 / 0.01 / 12, rel=1e-12)
    # a black reference: inf, or 0 against itself
    assert im.relmse(np.zeros((2, 2, 3)), np.zeros((2, 2, 3))) == 0.0
    assert im.relmse(np.full((2, 2, 3), 1e-9), np.zeros((2, 2, 3))) == math.inf
    with pytest.raises(ValueError):
        im.relmse(a, b, eps=0.0)


def test_mean_ratio():
    b = _smooth()
    assert im.mean_ratio(b, b) == 1.0
    assert im.mean_ratio(1.02 * b, b) == pytest.approx(1.02, rel=1e-12)
    a = b.copy()
    a[0, 0, 0] += b.sum()              # the whole image's worth of light in one value
    assert im.mean_ratio(a, b) == pytest.approx(2.0, rel=1e-12)
    assert im.mean_ratio(np.zeros((2, 2, 3)), np.zeros((2, 2, 3))) == 1.0
    assert im.mean_ratio(np.ones((2, 2, 3)), np.zeros((2, 2, 3))) == math.inf
    with pytest.raises(ImageError):
        im.mean_ratio(np.zeros((4, 5, 3)), np.zeros((5, 4, 3)))


def test_psnr_and_max_error_known_values():
    b = np.zeros((4, 4, 3))
    b[0, 0, 0] = 2.0  # peak 2
    a = b + 0.1  # mse 0.01
    assert im.psnr(a, b) == pytest.approx(10 * math.log10(4.0 / 0.01), abs=1e-9)
    assert im.psnr(a, b) == pytest.approx(26.0205999, abs=1e-6)
    c = b.copy()
    c[3, 2, 1] -= 0.7
    c[1, 1, 2] += 0.3
    assert im.max_error(c, b) == pytest.approx(0.7, abs=1e-15)
    assert im.rmse(c, b) == pytest.approx(math.sqrt((0.49 + 0.09) / 48), rel=1e-12)


def test_ssim_decreases_with_noise():
    ref = _smooth()
    rng = np.random.default_rng(4)
    noise = rng.standard_normal(ref.shape)
    values = [im.ssim(ref + s * noise, ref) for s in (0.0, 0.01, 0.05, 0.2)]
    assert values[0] == 1.0
    assert 1.0 > values[1] > values[2] > values[3]
    assert values[1] > 0.9 and values[3] < 0.5


@pytest.mark.parametrize("shape", [(1, 1, 3), (2, 5, 3), (3, 3, 3), (4, 9, 3), (6, 6, 3)])
def test_ssim_tiny_images(shape):
    rng = np.random.default_rng(5)
    ref = rng.random(shape)
    assert im.ssim(ref, ref) == 1.0
    noisy = ref + 0.3 * rng.standard_normal(shape)
    v = im.ssim(noisy, ref)
    assert math.isfinite(v) and v < 1.0
    if shape != (1, 1, 3):  # a single pixel has no structure; compare still works
        assert v < 0.99


def test_ssim_constant_reference_is_finite():
    ref = np.full((8, 8, 3), 0.5)
    assert im.ssim(ref, ref) == 1.0
    assert 0.0 < im.ssim(ref + 0.05, ref) < 1.0


@pytest.mark.parametrize(
    "func", [im.rmse, im.relmse, im.mean_ratio, im.psnr, im.ssim, im.max_error, im.compare, im.heatmap]
)
def test_shape_mismatch(func):
    with pytest.raises(ImageError) as exc:
        func(np.zeros((4, 5, 3)), np.zeros((5, 4, 3)))
    msg = _assert_one_line(exc)
    assert "(4, 5, 3)" in msg and "(5, 4, 3)" in msg


def test_to_json_safe():
    m = {"psnr": math.inf, "a": -math.inf, "b": math.nan, "rmse": 0.5}
    from clscatter.io.stats import json_safe
    safe = json_safe(m)
    assert safe == {"psnr": "inf", "a": "-inf", "b": "nan", "rmse": 0.5}
    json.dumps(safe, allow_nan=False)  # strict JSON
    assert m["psnr"] == math.inf  # input untouched


# -------------------------------------------------------------------- heatmap


def test_heatmap_shape_zero_and_top_colour(tmp_path):
    b = _smooth(10, 12)
    zero = im.heatmap(b, b)
    assert zero.dtype == np.uint8 and zero.shape == (10, 12, 3)
    zero_colour = np.array(colormaps["inferno"](0.0, bytes=True)[:3])
    top_colour = np.array(colormaps["inferno"](1.0, bytes=True)[:3])
    assert (zero == zero_colour).all()

    a = b.copy()
    a[3, 4] += 5.0  # one pixel with a large error; the 99th percentile is < 5
    h = im.heatmap(a, b)
    np.testing.assert_array_equal(h[3, 4], top_colour)
    assert (h[0, 0] == zero_colour).all()

    path = tmp_path / "heat.png"
    im.write_heatmap(path, a, b)
    np.testing.assert_array_equal(iio.imread(path), h)


def test_heatmap_robust_scale_and_nan():
    b = np.zeros((10, 10, 3))
    a = np.zeros((10, 10, 3))
    a[..., :] = np.linspace(0, 1, 100).reshape(10, 10, 1)  # error 0 .. 1
    a[9, 9] = 1000.0  # outlier above the 99th percentile
    a[0, 1] = np.nan
    h = im.heatmap(a, b)
    cmap = colormaps["inferno"]
    top = np.array(cmap(1.0, bytes=True)[:3])
    np.testing.assert_array_equal(h[9, 9], top)
    np.testing.assert_array_equal(h[0, 1], top)  # non-finite shown at the top
    # Mid-range pixels use the colour scale instead of being crushed to black.
    assert not (h[5, 0] == np.array(cmap(0.0, bytes=True)[:3])).all()


# ----------------------------------------------------------- errors, diff


def test_unknown_suffix_and_missing_file(tmp_path):
    with pytest.raises(ImageError) as exc:
        im.read_image(tmp_path / "picture.tiff")
    msg = _assert_one_line(exc)
    assert "picture.tiff" in msg and ".exr" in msg and ".png" in msg
    for name in ("absent.exr", "absent.npy", "absent.pfm", "absent.png"):
        with pytest.raises(ImageError) as exc:
            im.read_image(tmp_path / name)
        assert name in _assert_one_line(exc)


@pytest.mark.parametrize("name", ["junk.exr", "junk.npy", "junk.png", "junk.pfm"])
def test_corrupt_files(tmp_path, name):
    path = tmp_path / name
    path.write_bytes(b"this is not an image\nat all\n")
    with pytest.raises(ImageError) as exc:
        im.read_image(path)
    assert name in _assert_one_line(exc)


def test_diff_command_json(tmp_path, capsys):
    b = _smooth(16, 16).astype(np.float32)
    a = b + np.float32(0.125)
    pa, pb, ph = tmp_path / "a.npy", tmp_path / "b.exr", tmp_path / "heat.png"
    im.write_image(pa, a)
    im.write_image(pb, b)
    assert diff_command(pa, pb, heatmap_path=ph, as_json=True) == 0
    out = capsys.readouterr().out
    data = json.loads(out)
    assert set(data) == {"rmse", "relmse", "psnr", "ssim", "max_error"}
    assert data["rmse"] == pytest.approx(0.125, abs=1e-7)
    assert data["max_error"] == pytest.approx(0.125, abs=1e-7)
    assert iio.imread(ph).shape == (16, 16, 3)

    assert diff_command(pb, pb, as_json=True) == 0
    data = json.loads(capsys.readouterr().out)
    assert data["psnr"] == "inf" and data["rmse"] == 0 and data["ssim"] == 1


def test_diff_command_text(tmp_path, capsys):
    b = _smooth(8, 8).astype(np.float32)
    im.write_image(tmp_path / "b.pfm", b)
    im.write_image(tmp_path / "a.pfm", b * 1.1)
    assert diff_command(tmp_path / "a.pfm", tmp_path / "b.pfm") == 0
    lines = capsys.readouterr().out.strip().splitlines()
    assert [ln.split(":")[0] for ln in lines] == ["rmse", "relmse", "psnr", "ssim", "max_error"]
    assert float(lines[0].split(":")[1]) == pytest.approx(im.rmse(b * 1.1, b), rel=1e-5)
    assert lines[2].endswith("dB")


def test_diff_command_errors(tmp_path):
    im.write_image(tmp_path / "small.npy", np.zeros((4, 5, 3)))
    im.write_image(tmp_path / "big.npy", np.zeros((5, 4, 3)))
    with pytest.raises(ImageError) as exc:
        diff_command(tmp_path / "small.npy", tmp_path / "big.npy")
    msg = _assert_one_line(exc)
    assert "small.npy" in msg and "big.npy" in msg
    assert "(4, 5, 3)" in msg and "(5, 4, 3)" in msg
    with pytest.raises(ImageError) as exc:
        diff_command(tmp_path / "small.npy", tmp_path / "nothere.exr")
    assert "nothere.exr" in _assert_one_line(exc)


def test_linear_and_tone_mapped_formats():
    """PNG is the only tone-mapped format; check_comparable refuses exactly the mixed pairs,
    naming both files in one line."""
    assert im.is_tone_mapped("a.png") and im.is_tone_mapped("A.PNG")
    assert not any(im.is_tone_mapped(f"a.{s}") for s in ("exr", "npy", "pfm", "EXR"))
    assert set(im.LINEAR_SUFFIXES) | set(im.TONE_MAPPED_SUFFIXES) == set(im.SUPPORTED_SUFFIXES)
    for a, b in [("a.exr", "b.npy"), ("a.pfm", "b.exr"), ("a.png", "b.PNG")]:
        im.check_comparable(a, b)                                # like with like: no error
    for a, b in [("a.exr", "b.png"), ("a.png", "b.npy"), ("x/a.PNG", "b.pfm")]:
        with pytest.raises(ImageError) as e:
            im.check_comparable(a, b)
        msg = str(e.value)
        assert a in msg and b in msg and "\n" not in msg
        assert "linear" in msg and "tone-mapped" in msg and "two PNGs" in msg
    with pytest.raises(ImageError, match="unsupported image format"):
        im.is_tone_mapped("a.gif")


def test_diff_command_refuses_png_against_exr(tmp_path, capsys):
    img = np.full((3, 4, 3), 0.25, np.float32)
    im.write_image(tmp_path / "a.exr", img)
    im.write_image(tmp_path / "b.png", img)
    with pytest.raises(ImageError, match="comparing a linear image with a tone-mapped one"):
        diff_command(tmp_path / "a.exr", tmp_path / "b.png", heatmap_path=tmp_path / "h.png")
    assert capsys.readouterr().out == "" and not (tmp_path / "h.png").exists()
