"""``python -m clscatter.serve SCENE [--port P] ...``: the serve command on its own (the same
parser and errors as ``clscatter serve``; useful before the main CLI wires it in)."""
from __future__ import annotations

import argparse
import sys

from ..errors import ClscatterError
from . import add_serve_command, cmd_serve


def main(argv: list[str] | None = None) -> int:
    """Parse ``argv`` as ``clscatter serve`` arguments and run it; the exit status."""
    parser = argparse.ArgumentParser(prog="clscatter")
    sub = parser.add_subparsers(dest="command")
    add_serve_command(sub)
    args = parser.parse_args(["serve", *(sys.argv[1:] if argv is None else argv)])
    try:
        return cmd_serve(args)
    except ClscatterError as e:
        print(f"clscatter: error: {' '.join(str(e).split())}", file=sys.stderr)
        return e.exit_status
    except KeyboardInterrupt:
        return 130


if __name__ == "__main__":
    sys.exit(main())
