"""Write the procedural meshes of the caustic scenes as OBJ files (committed data).

    python3 tools/make_caustic_meshes.py

writes ``clscatter/scene/meshes/{torus,gem,dish,blob}.obj`` from
``clscatter/scene/procedural.py`` and prints their sizes and triangle counts; rerun it
only when a generator changes.
"""
from __future__ import annotations

import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from clscatter.scene.procedural import MESHES, write_obj  # noqa: E402

OUT = REPO / "clscatter" / "scene" / "meshes"


def main() -> None:
    OUT.mkdir(parents=True, exist_ok=True)
    for name, make in MESHES.items():
        v, f = make()
        path = OUT / f"{name}.obj"
        write_obj(path, v, f)
        print(f"{path.relative_to(REPO)}: {len(f)} triangles, {path.stat().st_size / 1024:.0f} KB")


if __name__ == "__main__":
    main()
