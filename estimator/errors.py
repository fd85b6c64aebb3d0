"""Errors of the tapecell project.

Every package raises subclasses of :class:`TapecellError` where a fault is found; the
``tapecell`` command prints their message as one line and exits with the error's
``exit_code``:

    0  done
    1  the task itself failed (:class:`TaskFailed`: a grasp missed, a fit or a motion refused)
    2  bad input or usage (:class:`TapecellError` and its other subclasses)
    3  the robot or other hardware failed (:class:`HardwareError`: no answer, a dropped link)
"""


class TapecellError(Exception):
    """Base of every error the user can cause (bad files, bad poses, bad options)."""

    exit_code = 2


class TaskFailed(TapecellError):
    """The inputs were fine but the task could not be done (a fit not trustworthy enough to
    act on, a grasp refused or missed, a calibration that does not converge)."""

    exit_code = 1


class HardwareError(TapecellError):
    """The robot, a camera or other hardware did not answer or failed."""

    exit_code = 3


class CaptureError(TapecellError):
    """A capture, cameras or truth file is missing, malformed or inconsistent."""


class EstimateError(TapecellError):
    """The estimator was given inputs it cannot fit."""


class OutputError(TapecellError):
    """An output file or folder cannot be written, or writing it would lose a user's file."""
