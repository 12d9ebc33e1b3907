"""Pieces the built-in scenes share: camera, floor, render settings at the built-ins' size."""
from __future__ import annotations

CAMERA = {"resolution": [320, 240], "spp": 4}
RENDER = {"method": "auto", "max_depth": 16, "seed": 0}


def camera(origin: list[float], target: list[float], fov: float) -> dict:
    return {"origin": origin, "target": target, "up": [0.0, 1.0, 0.0], "fov": fov,
            "fov_axis": "x", **CAMERA}


def floor(half: float = 4.0, material: str = "floor") -> dict:
    return {"shape": "quad", "origin": [-half, 0.0, -half], "edge_u": [2 * half, 0.0, 0.0],
            "edge_v": [0.0, 0.0, 2 * half], "material": material}
