"""tapecell: estimate floppy tape from camera silhouettes and grasp its tip with a UR arm.

The repository's root is this package (``pyproject.toml`` maps it): ``tapecell.estimator``
(images to tape, no robots, no MuJoCo), ``tapecell.cell`` (the real cell: cell file,
calibration, planner, UR driver, recording), ``tapecell.sim`` (the MuJoCo cell, episodes,
campaigns) and ``tapecell.cli`` (the ``tapecell`` command, on top of all three).
"""
import os as _os
from pathlib import Path as _Path

__version__ = "0.2.0"


def cache_dir() -> _Path:
    """The user's cache folder for tapecell ($XDG_CACHE_HOME/tapecell, ~/.cache/tapecell):
    compiled kernels live here, never inside an installed package (a leftover cache folder
    in site-packages shadows a later editable install)."""
    base = _os.environ.get("XDG_CACHE_HOME") or _os.path.join(_os.path.expanduser("~"), ".cache")
    return _Path(base) / "tapecell"


# numba reads NUMBA_CACHE_DIR when it is first imported (by tapecell.estimator._kernels).
_os.environ.setdefault("NUMBA_CACHE_DIR", str(cache_dir() / "numba"))
