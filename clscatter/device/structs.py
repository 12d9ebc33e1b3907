"""NumPy dtypes mirroring C structs of ``cl_kernels/``, and the registry of all of them.

One place for each host/device struct: the dtypes of ``common.h`` are here; a method's own
structs live in its package and are registered with :func:`register_struct`. The layout
test (``tests/test_structs.py``) compiles a kernel that reports ``sizeof`` and ``offsetof``
of every registered struct and compares them with the dtypes, so the two declarations
cannot drift apart silently; it also fails on a ``typedef struct`` in a kernel file that is
neither registered nor listed in :data:`DEVICE_ONLY`.
"""
from __future__ import annotations

import numpy as np

F4 = (np.float32, 4)

# Material.type values (MAT_* in common.h)
MAT_DIFFUSE, MAT_MIRROR, MAT_DIELECTRIC, MAT_BLACK = 0, 1, 2, 3
MATERIAL_TYPES = {"diffuse": MAT_DIFFUSE, "mirror": MAT_MIRROR,
                  "dielectric": MAT_DIELECTRIC, "black": MAT_BLACK}

# Light.type values (LIGHT_* in common.h)
LIGHT_POINT, LIGHT_SPOT, LIGHT_DIRECTIONAL = 0, 1, 2
LIGHT_TYPES = {"point": LIGHT_POINT, "spot": LIGHT_SPOT, "directional": LIGHT_DIRECTIONAL}

MATERIAL = np.dtype([
    ("color", *F4), ("interior_sigma_a", *F4), ("interior_sigma_s", *F4),
    ("ior", np.float32), ("type", np.int32), ("pad0", np.int32), ("pad1", np.int32),
], align=True)

LIGHT = np.dtype([
    ("position", *F4), ("direction", *F4), ("power", *F4),
    ("cos_cutoff", np.float32), ("type", np.int32), ("pad0", np.int32), ("pad1", np.int32),
], align=True)

MEDIUM = np.dtype([
    ("sigma_s", *F4), ("sigma_a", *F4), ("kappa", *F4), ("bmin", *F4), ("bmax", *F4),
    ("g", np.float32), ("present", np.int32), ("bounded", np.int32), ("t_far", np.float32),
], align=True)

CAMERA = np.dtype([
    ("origin", *F4), ("forward", *F4), ("right", *F4), ("up", *F4),
    ("width", np.int32), ("height", np.int32), ("spp", np.int32), ("spp_side", np.int32),
    ("inside", np.int32), ("radiance_scale", np.float32), ("pad0", np.int32), ("pad1", np.int32),
], align=True)

BVH_NODE = np.dtype([
    ("bmin", np.float32, 3), ("left_first", np.int32),
    ("bmax", np.float32, 3), ("count", np.int32),
], align=True)

def _segment(value: str, owner: str, index: str) -> np.dtype:
    """The one layout of a straight path piece (64 bytes): ends a, b, an rgb ``value``, the
    ``owner`` (pixel or light), the specular depth, the ``index`` of the path (camera sample
    or lighting ray) and the branch within that path's tree. View and light segments share
    it; their fields keep their own names because they mean different things."""
    return np.dtype([("a", *F4), ("b", *F4), (value, *F4), (owner, np.int32),
                     ("depth", np.int32), (index, np.int32), ("branch", np.int32)], align=True)


VIEW_SEGMENT = _segment("weight", "pixel", "sample")
LIGHT_SEGMENT = _segment("flux", "light", "ray")


def segment_regions(segs: np.ndarray) -> np.ndarray:
    """The region of every view or light segment (int32): 0 in the scene medium, m + 1
    inside dielectric material m (the w lane of ``a``, common.h: only the tracers built
    with ``SEGMENT_REGIONS & 2`` write anything but 0 there)."""
    return np.rint(segs["a"][:, 3]).astype(np.int32)

# RayPiece.end values (PIECE_* in common.h)
PIECE_DIFFUSE, PIECE_BLACK, PIECE_ESCAPED = 0, 1, 2

RAY_PIECE = np.dtype([
    ("a", *F4), ("b", *F4), ("flux", *F4),
    ("light", np.int32), ("depth", np.int32), ("ray", np.int32), ("branch", np.int32),
    ("end", np.int32), ("pad0", np.int32), ("pad1", np.int32), ("pad2", np.int32),
], align=True)

DIFFUSE_HIT = np.dtype([
    ("p", *F4), ("n", *F4), ("g", *F4), ("weight", *F4),
    ("pixel", np.int32), ("sample", np.int32), ("depth", np.int32), ("branch", np.int32),
], align=True)

# C struct name -> (header that declares it, host dtype)
REGISTRY: dict[str, tuple[str, np.dtype]] = {}

# structs that live and die inside a kernel (no host copy exists, so no twin is needed)
DEVICE_ONLY = frozenset({"Hit", "BvhRay", "Rng", "Branch", "SurfaceFrame", "ViewQuery", "Tri",
                         "Pending", "Walk", "TreeWalk", "LeafScan"})


def register_struct(header: str, cname: str, dtype: np.dtype) -> np.dtype:
    """Declare that ``dtype`` mirrors ``typedef struct {...} cname`` of ``cl_kernels/header``."""
    REGISTRY[cname] = (header, np.dtype(dtype))
    return dtype


# the structs of common.h
ALL = {"Material": MATERIAL, "Light": LIGHT, "Medium": MEDIUM, "Camera": CAMERA,
       "BVHNode": BVH_NODE, "ViewSegment": VIEW_SEGMENT,
       "LightSegment": LIGHT_SEGMENT, "RayPiece": RAY_PIECE, "DiffuseHit": DIFFUSE_HIT}
for _name, _dt in ALL.items():
    register_struct("common.h", _name, _dt)


def vec4(xyz, w: float = 0.0) -> np.ndarray:
    """A float32 4-vector from an xyz triple (the w lane padded)."""
    v = np.zeros(4, np.float32)
    v[:3] = np.asarray(xyz, dtype=np.float64)
    v[3] = w
    return v
