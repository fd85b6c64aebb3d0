"""Errors of the tapecell project.

Every package raises subclasses of :class:`TapecellError` where a fault is found; the
``tapecell`` command prints their message as one line and exits with status 2.
"""


class TapecellError(Exception):
    """Base of every error the user can cause (bad files, bad poses, unreachable robot)."""


class CaptureError(TapecellError):
    """A capture, cameras or truth file is missing, malformed or inconsistent."""


class EstimateError(TapecellError):
    """The estimator was given inputs it cannot fit."""
