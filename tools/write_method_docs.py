"""Write docs/methods.md from the method classes (their PARAMS, TERMS, AUTO and docstrings).

Run after changing a method's parameters: ``.venv/bin/python tools/write_method_docs.py``.
``tests/test_methods.py`` fails while the committed file is out of date.
"""
from __future__ import annotations

import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from clscatter.methods import methods_markdown  # noqa: E402

if __name__ == "__main__":
    out = ROOT / "docs" / "methods.md"
    out.write_text(methods_markdown())
    print(f"wrote {out}")
