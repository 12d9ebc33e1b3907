"""clscatter: single scattering in participating media, rendered with OpenCL.

The Python API (:mod:`clscatter.api`)::

    import clscatter

    scene = clscatter.load("builtin:caustic_sphere")     # a TOML path, a dict, or "builtin:NAME"
    result = clscatter.render(scene, method="auto")       # .image (H, W, 3) float32, .stats
    clscatter.write(result, "sphere.exr", "sphere.png")   # all or nothing

    with clscatter.Session(scene) as session:             # warm re-renders
        params = session.params                           # {"lights[0].position": [...], ...}
        params["lights[0].position"] = [0.5, 3.0, 0.0]
        session.update(params)                            # applies the changed keys only
        result = session.render()

Importing this package is cheap: the names in ``__all__`` are loaded lazily, on first
attribute access (PEP 562 module ``__getattr__``), so ``import clscatter`` (which the
command line does) starts neither NumPy nor OpenCL. ``clscatter.load`` imports the scene
loader (NumPy); OpenCL starts with the first render. Subpackages (``clscatter.scene``,
``clscatter.pipeline``, ...) import as usual.
"""
__version__ = "0.1.0"

# public name -> module that defines it (imported on first access)
_LAZY = {
    "load": "clscatter.api",
    "render": "clscatter.api",
    "write": "clscatter.api",
    "Session": "clscatter.api",
    "SceneSpec": "clscatter.api",
    "RenderResult": "clscatter.pipeline.render",
    "ClscatterError": "clscatter.errors",
    "SceneError": "clscatter.errors",
    "ImageError": "clscatter.errors",
    "DeviceError": "clscatter.errors",
}

__all__ = [
    "ClscatterError", "DeviceError", "ImageError", "RenderResult", "SceneError", "SceneSpec",
    "Session", "__version__", "load", "render", "write",
]    # the names of _LAZY, and the version


def __getattr__(name: str):
    """Load a public name of ``__all__`` on first access (and keep it in the module)."""
    module = _LAZY.get(name)
    if module is None:
        # an AttributeError lets ``from clscatter import <subpackage>`` import it
        raise AttributeError(f"module 'clscatter' has no attribute {name!r}")
    from importlib import import_module

    value = getattr(import_module(module), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(_LAZY))
