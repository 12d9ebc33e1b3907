"""Where ``scripts/setup.sh`` installs the system tools some tests need (Chromium for the
browser test, Oclgrind for the second OpenCL implementation): there a missing tool makes
those tests fail, so they cannot pass by not running; anywhere else they skip."""
from __future__ import annotations

import os
import shutil


def setup_installs_here(env=None, which=shutil.which, euid=None) -> str | None:
    """Why this machine must have what ``scripts/setup.sh`` installs, or None where a
    missing tool may be skipped: under CI (``CI`` set), or as root where ``apt-get``
    exists."""
    env = os.environ if env is None else env
    uid = (os.geteuid() if hasattr(os, "geteuid") else -1) if euid is None else euid
    if env.get("CI"):
        return "CI is set"
    if which("apt-get") and uid == 0:
        return "we are root on a machine with apt-get"
    return None
