"""The method plug-in mechanism: parameters declared once and checked before device work,
keyword kernel launches checked against the kernel's declaration, generated docs."""
from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from clscatter.errors import KernelArgError, SceneError
from clscatter.methods import (
    Method,
    Param,
    all_methods,
    configure,
    get_method,
    methods_markdown,
    param_table,
)
from clscatter.methods.base import TERMS
from clscatter.scene import load_scene

REPO = Path(__file__).resolve().parents[1]
OPTIONAL = ("tqdm", "scipy", "matplotlib", "OpenEXR", "Imath", "imageio", "skimage", "trimesh",
            "pyopencl")


def _cli_without(modules, *args):
    """Run the CLI in a fresh process where importing any of ``modules`` fails."""
    code = ("import sys\n"
            f"for m in {tuple(modules)!r}: sys.modules[m] = None\n"
            "from clscatter.cli import main\n"
            "sys.exit(main(sys.argv[1:]))\n")
    return subprocess.run([sys.executable, "-c", code, *args], capture_output=True, text=True,
                          timeout=120, cwd=REPO)


def test_misspelled_key_is_reported_with_every_optional_dependency_missing(tmp_path):
    out = tmp_path / "x.png"
    r = _cli_without(OPTIONAL, "render", "builtin:shafts", "--set", "render.raymarch.stepz=3",
                     "-o", str(out))
    assert r.returncode == 2, r.stderr
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and "render.raymarch.stepz" in lines[0] and "did you mean 'steps'" in lines[0]
    assert not out.exists()
    r = _cli_without(OPTIONAL, "render", "builtin:shafts", "--set", "render.vpm.knn=1",
                     "-o", str(out))
    assert r.returncode == 2 and "render.vpm.knn: must be in [2, 1024] (got 1)" in r.stderr


def test_range_errors_come_before_any_device_work(monkeypatch):
    import clscatter.pipeline.render as render_mod
    import clscatter.pipeline.session as session_mod

    def no_device(*a, **k):
        raise AssertionError("a device was requested before the parameters were checked")

    monkeypatch.setattr(session_mod, "get_engine", no_device)
    monkeypatch.setattr(session_mod, "prepare_scene", no_device)
    # an unused method's table is still checked
    scene = load_scene("builtin:shafts", ["render.lsg.radius=-0.01"])
    with pytest.raises(SceneError) as e:
        render_mod.render(scene, method="raymarch")
    assert e.value.key == "render.lsg.radius"
    with pytest.raises(SceneError) as e:
        render_mod.render(load_scene("builtin:shafts"), method="")
    assert e.value.key == "render.method"
    with pytest.raises(SceneError) as e:
        render_mod.render(load_scene("builtin:shafts"), method="raymarchh")
    assert e.value.key == "render.method"


def test_param_checks():
    p = Param("x", 0.5, "a number", lo=0, hi=1, lo_open=True)
    assert p.check(1, "k") == 1.0 and isinstance(p.check(1, "k"), float)
    for bad, msg in ((0, "must be in (0, 1]"), (1.5, "must be in (0, 1]"), (True, "expected a number"),
                     ("a", "expected a number"), (float("nan"), "finite"), (float("inf"), "finite")):
        with pytest.raises(SceneError, match=msg.replace("(", r"\(").replace("[", r"\[")
                           .replace("]", r"\]").replace(")", r"\)")):
            p.check(bad, "k")
    i = Param("n", 3, "an int", lo=1)
    with pytest.raises(SceneError, match="expected an integer"):
        i.check(2.0, "k")
    c = Param("mode", "a", "a choice", choices=("a", "b"))
    with pytest.raises(SceneError, match="must be one of 'a', 'b'"):
        c.check("c", "k")


def test_every_method_declares_itself_completely():
    known = all_methods()
    assert {"raymarch", "lsg", "vpm", "epipolar"} <= set(known)
    for name, cls in known.items():
        assert issubclass(cls, Method) and cls.NAME == name
        assert cls.TERMS and set(cls.TERMS) <= set(TERMS)
        assert set(cls.AUTO) <= set(cls.TERMS)
        for p in cls.PARAMS:
            assert p.doc and p.type in (bool, int, float, str), (name, p.name)
            p.check(p.default, f"render.{name}.{p.name}")      # defaults are in range
        assert configure(name, None) == {p.name: p.default for p in cls.PARAMS}
        assert "\n".join("    " + r for r in param_table(cls).splitlines()) in cls.__doc__
        assert get_method(name) is cls


def test_committed_method_docs_are_current():
    doc = (REPO / "docs" / "methods.md").read_text()
    assert doc == methods_markdown(), "run: .venv/bin/python tools/write_method_docs.py"


# ---- keyword kernel launches ------------------------------------------------------------

@pytest.mark.parametrize("cost, sizes", [
    (1e-4, [1024, 2500, 2500]),              # 2,500 items fill a quarter second
    (1e-8, [1024, 4096, 16384, 65536]),      # cheap items: growth by 4 up to the most
    (1e-1, [1024, 2, 2, 2]),                 # dear items: down to what fits
])
def test_timed_launches_cover_the_items_in_launches_of_about_a_quarter_second(cost, sizes):
    from clscatter.device.launch import timed_launches
    now = [0.0]
    got, end, n = [], 0, 200_000
    for start, count in timed_launches(n, 65536, clock=lambda: now[0]):
        assert start == end and count >= 1
        now[0] += count * cost                      # the launch, finished
        got.append(count)
        end = start + count
    assert end == n
    assert got[:len(sizes)] == sizes
    assert all(c <= 4 * b for b, c in zip(got, got[1:]))

def test_kernel_signature_parsing():
    from clscatter.device import kernel_signature
    src = """
    /* __kernel void decoy(int a) */
    __kernel void k(__global const float4 *restrict pts, // points
                    int n, float4 centre, volatile __global int *count,
                    __global const MyStruct *s) { }
    """
    sig = kernel_signature(src, "k")
    assert [(p.name, p.ctype, p.pointer) for p in sig] == [
        ("pts", "float4*", True), ("n", "int", False), ("centre", "float4", False),
        ("count", "volatile int*", True), ("s", "MyStruct*", True)]
    with pytest.raises(KernelArgError, match="decoy"):
        kernel_signature(src, "decoy")


def test_kernel_signature_follows_cl_includes(tmp_path):
    """A kernel defined in a ``.cl`` file that the program's file ``#include``s is found
    (``voxel_direct.cl`` builds ``raymarch.cl``'s kernel); headers are not entry points."""
    from clscatter.device import program_signature
    (tmp_path / "a.cl").write_text('#include "h.h"\n// #include "decoy.cl"\n#include "b.cl"\n'
                                   "__kernel void own(int x) { }\n")
    (tmp_path / "b.cl").write_text('#include "c.cl"\n__kernel void mid(float y) { }\n')
    (tmp_path / "c.cl").write_text("__kernel void deep(__global int *z, int n) { }\n")
    (tmp_path / "decoy.cl").write_text("__kernel void decoy(int q) { }\n")
    assert [p.name for p in program_signature("a", "own", tmp_path)] == ["x"]
    assert [p.name for p in program_signature("a", "mid", tmp_path)] == ["y"]
    assert [(p.name, p.pointer) for p in program_signature("a", "deep", tmp_path)] == [
        ("z", True), ("n", False)]
    with pytest.raises(KernelArgError, match="decoy"):
        program_signature("a", "decoy", tmp_path)
    assert program_signature("voxel_direct", "raymarch") == program_signature("raymarch", "raymarch")


def test_keyword_launch_runs_and_checks_names(engine):
    a = np.arange(16, dtype=np.float32)
    ab, ob = engine.to_device(a), engine.empty(a.nbytes)
    try:
        engine.call("probe", "probe", 16, a=ab, n=16, out=ob)
        np.testing.assert_allclose(engine.read(ob, 16, np.float32), a * a + 6.0)
        with pytest.raises(KernelArgError, match="no parameter 'outt'.*did you mean 'out'"):
            engine.call("probe", "probe", 16, a=ab, n=16, outt=ob)
        with pytest.raises(KernelArgError, match="missing argument.*out"):
            engine.call("probe", "probe", 16, a=ab, n=16)
        with pytest.raises(KernelArgError, match="'a'.*needs a device buffer"):
            engine.call("probe", "probe", 16, a=a, n=16, out=ob)
    finally:
        engine.free(ab, ob)


def test_scalars_are_converted_to_the_declared_type(engine):
    """``steps=3`` becomes a 32-bit int and ``seed`` a uint where the kernel says so."""
    args = engine.bind("raymarch", "raymarch", {
        "nodes": engine.empty(4), "tris": engine.empty(4), "light_grid": engine.empty(4),
        "lights": engine.empty(4), "num_lights": 1, "medium": engine.empty(4), "segs": engine.empty(4), "seg_offset": 0,
        "num_segs": 5, "scale": engine.empty(4), "use_scale": 0, "steps": 3, "seed": 7,
        "out": engine.empty(4)})
    assert [type(a) for a in args[4:5]] == [np.int32]
    assert isinstance(args[11], np.int32) and isinstance(args[12], np.uint32)


def test_preview_parameters_scale_the_costly_ones():
    lsg = get_method("lsg")
    p = lsg.preview({"light_rays": 80_000, "time_budget": 10.0, "passes": 8})
    assert p == {"light_rays": 10_000, "time_budget": 0.0, "passes": 1}
    assert lsg.preview({})["light_rays"] == 25_000          # from the default
    for name, cls in all_methods().items():
        configure(name, cls.preview({}))                     # previews stay in range
