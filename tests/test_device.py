"""Device choice survives broken platforms, honours explicit choices, builds with a
binary cache and reports build errors with the compiler log."""
from __future__ import annotations

import pyopencl as cl
import pytest

from clscatter import device as dev
from clscatter.device import choice, kernel_sources, programs
from clscatter.errors import DeviceError, KernelBuildError


class _BrokenPlatform:
    """Stands in for the PyPI PoCL wheel on this CPU: listing devices fails."""
    name = "Broken Platform"

    def get_devices(self):
        raise cl.RuntimeError("clGetDeviceIDs failed: unknown target CPU 'generic'")


class _BadDevice:
    """A device that lists fine but cannot build the probe."""
    name = "Bad Device"
    type = cl.device_type.CPU


class _HalfBrokenPlatform:
    name = "Half Broken"

    def get_devices(self):
        return [_BadDevice()]


@pytest.fixture
def with_broken_platforms(monkeypatch):
    real = cl.get_platforms()
    monkeypatch.setattr(cl, "get_platforms", lambda: [_BrokenPlatform(), _HalfBrokenPlatform(), *real])
    monkeypatch.delenv(dev.ENV_DEVICE, raising=False)
    return real


def test_real_device_probes_ok():
    infos, _ = dev.list_devices()
    assert any(i.ok for i in infos)


def test_broken_platforms_are_skipped_with_reasons(with_broken_platforms):
    infos, problems = dev.list_devices()
    assert any("unknown target CPU" in p and "platform 0" in p for p in problems)
    bad = [i for i in infos if i.name == "Bad Device"]
    assert bad and not bad[0].ok and bad[0].reason
    chosen = dev.choose_device()
    assert chosen.ok and chosen.platform_index >= 2


def test_explicit_choice_is_honoured_or_refused(with_broken_platforms, monkeypatch):
    assert dev.choose_device("2:0").platform_index == 2
    name = with_broken_platforms[0].get_devices()[0].name.strip()
    assert dev.choose_device(name[:12].lower()).name == name
    with pytest.raises(DeviceError, match="not found"):
        dev.choose_device("no-such-device")
    # an explicit choice of a failing device is an error, never a silent fallback
    with pytest.raises(DeviceError, match="fails its probe"):
        dev.choose_device("1:0")
    monkeypatch.setenv(dev.ENV_DEVICE, "no-such-device")
    with pytest.raises(DeviceError, match="no-such-device"):
        dev.choose_device()


def test_binary_cache_skips_recompilation(tmp_path, monkeypatch):
    monkeypatch.setenv(dev.ENV_CACHE, str(tmp_path))
    info = dev.choose_device()
    e1 = dev.Engine(info)
    e1.program("probe", {"CACHE_TEST": 1})
    assert e1.builds == {"source": 1, "cache": 0}
    assert len(list(tmp_path.glob("probe-*.bin"))) == 1
    e2 = dev.Engine(info)
    e2.program("probe", {"CACHE_TEST": 1})
    assert e2.builds == {"source": 0, "cache": 1}
    e2.program("probe", {"CACHE_TEST": 2})          # other options: another binary
    assert e2.builds == {"source": 1, "cache": 1}
    assert len(list(tmp_path.glob("probe-*.bin"))) == 2


@pytest.mark.parametrize("kind, hint", [
    (cl.device_type.CPU, True),
    (cl.device_type.CPU | cl.device_type.DEFAULT, True),     # a platform's default device
    (cl.device_type.GPU, False),
    # Oclgrind claims every type and cannot lower a prefetch
    (cl.device_type.CPU | cl.device_type.GPU | cl.device_type.ACCELERATOR
     | cl.device_type.DEFAULT, False),
])
def test_cache_prefetch_hints_only_on_a_cpu_device(kind, hint):
    class _Device:
        type = kind
    defines = programs.device_defines(cl, _Device())
    assert ("CLSCATTER_CPU_PREFETCH" in defines) is hint


def test_build_error_carries_the_compiler_log(tmp_path, monkeypatch):
    (tmp_path / "broken.cl").write_text('#include "common.h"\n__kernel void k(__global float *a) '
                                        '{ a[0] = undefined_symbol_xyz; }\n')
    e = dev.Engine(dev.choose_device())
    monkeypatch.setattr(kernel_sources, "_EXTRA_DIRS", [tmp_path])
    monkeypatch.setenv(dev.ENV_CACHE, str(tmp_path / "cache"))
    with pytest.raises(KernelBuildError, match="undefined_symbol_xyz"):
        e.program("broken")


def test_buffers_are_tracked(engine):
    import numpy as np
    before = engine.bytes_live
    b = engine.to_device(np.zeros(1000, np.float32))
    assert engine.bytes_live == before + 4000 and engine.bytes_peak >= before + 4000
    engine.free(b)
    assert engine.bytes_live == before


def test_probe_results_are_cached_across_runs(tmp_path, monkeypatch):
    """A device that passed its probe is not probed again while platform, device and
    driver versions are unchanged; ``clscatter devices`` (list_devices) always probes."""
    monkeypatch.setenv(dev.ENV_CACHE, str(tmp_path))
    calls = []
    real_probe = choice._probe
    monkeypatch.setattr(choice, "_probe", lambda d: calls.append(d) or real_probe(d))
    monkeypatch.delenv(dev.ENV_DEVICE, raising=False)
    first = dev.choose_device()
    assert len(calls) == 1 and (tmp_path / "probe.json").is_file()
    second = dev.choose_device()
    assert len(calls) == 1 and second.label == first.label
    dev.list_devices(probe=True)
    assert len(calls) == 1 + len(dev.list_devices(probe=False)[0])


def test_program_files_follow_includes_transitively(tmp_path):
    """The binary cache key reads a program's own source and what it includes, directly
    or not (a header edit invalidates the programs using it, and only those); comments
    and missing files are ignored."""
    from clscatter.device import program_files
    (tmp_path / "a.cl").write_text('#include "b.h"\n  # include "c.cl"\n/* #include "z.h" */\n')
    (tmp_path / "b.h").write_text('#include "d.h"\n')
    (tmp_path / "c.cl").write_text('#include "b.h"\n#include "missing.h"\n')
    (tmp_path / "d.h").write_text("")
    (tmp_path / "z.h").write_text("")
    (tmp_path / "other.cl").write_text('#include "z.h"\n')
    assert [p.name for p in program_files("a", tmp_path)] == ["a.cl", "b.h", "c.cl", "d.h"]
    assert [p.name for p in program_files("other", tmp_path)] == ["other.cl", "z.h"]
    real = {p.name for p in program_files("primitives")}
    assert real == {"primitives.cl"}
    assert {"common.h", "bvh.h", "epipolar.h", "epipolar.cl"} <= {p.name for p in program_files("epipolar")}


def test_signatures_follow_edits_and_the_first_definition(tmp_path):
    """Signatures are parsed once per file, again when the file changes; a kernel found
    in an included .cl file; of two definitions of one name the first counts."""
    import os

    from clscatter.device import program_signature
    k = tmp_path / "k.cl"
    k.write_text('#include "inc.cl"\n__kernel void f(__global float *a, int n) {}\n'
                 "__kernel void f(int other) {}\n")
    (tmp_path / "inc.cl").write_text("__kernel void g(__global const int *x, float s) {}\n")
    assert [(p.name, p.ctype) for p in program_signature("k", "f", tmp_path)] == \
        [("a", "float*"), ("n", "int")]
    assert [p.name for p in program_signature("k", "g", tmp_path)] == ["x", "s"]
    k.write_text("__kernel void f(__global float4 *b, int n, uint seed) {}\n")
    st = k.stat()
    os.utime(k, ns=(st.st_atime_ns, st.st_mtime_ns + 10**9))   # a later edit
    assert [p.name for p in program_signature("k", "f", tmp_path)] == ["b", "n", "seed"]


def test_launch_pads_to_whole_groups_and_kernels_stop_at_their_count(engine):
    """1-D launches run in groups of GROUP_SIZE (one compiled variant per kernel on
    drivers that specialise by group size): the global size is rounded up and the kernel
    returns past its count, so a 3-element launch touches only its 3 elements."""
    import numpy as np

    from clscatter.device import GROUP_SIZE
    a = np.arange(3, dtype=np.float32)
    guard = np.full(GROUP_SIZE, -7.0, np.float32)
    ab, ob = engine.to_device(a), engine.to_device(np.concatenate([np.zeros(3, np.float32), guard]),
                                                   writable=True)
    try:
        engine.call("probe", "probe", 3, a=ab, n=3, out=ob)
        out = engine.read(ob, 3 + GROUP_SIZE, np.float32)
    finally:
        engine.free(ab, ob)
    np.testing.assert_allclose(out[:3], a * a + 6.0)
    np.testing.assert_array_equal(out[3:], guard)
    assert 1 <= engine._group_size(engine.kernel("probe", "probe")) <= GROUP_SIZE
