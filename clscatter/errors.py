"""User-facing errors: each becomes one line on stderr and exit status 2 in the CLI."""
from __future__ import annotations


class ClscatterError(Exception):
    """Base class for errors the user can fix (bad scene, file, option or device)."""

    exit_status = 2


class SceneError(ClscatterError):
    """A scene file or override is invalid. ``key`` is the dotted path of the culprit."""

    def __init__(self, key: str, message: str):
        self.key = key
        super().__init__(f"{key}: {message}" if key else message)


class DeviceError(ClscatterError):
    """No usable OpenCL device, or the one asked for does not exist or fails."""


class KernelBuildError(ClscatterError):
    """An OpenCL program failed to build; the message carries the compiler log."""

    exit_status = 1


class ImageError(ClscatterError):
    """An image file cannot be read or written."""


class KernelArgError(TypeError):
    """A kernel was launched with a wrong, missing or unknown keyword argument.

    A programming error, not a user one: it is deliberately not a :class:`ClscatterError`,
    so it surfaces as a traceback instead of a one-line message.
    """
