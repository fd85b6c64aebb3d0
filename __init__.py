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


def kernel_sources_digest(folder: _Path | None = None) -> str:
    """12 hex digits naming the estimator's compiled kernels' sources (every ``_kernels*.py``
    in ``folder``, the estimator's by default): numba's cache is kept per digest, because a
    kernel compiled into another file's (estimator/_kernels_lm.py holds copies of the
    residual kernels) is not recompiled when only the file it comes from changes."""
    import hashlib

    folder = _Path(__file__).resolve().parent / "estimator" if folder is None else _Path(folder)
    digest = hashlib.sha256()
    for path in sorted(folder.glob("_kernels*.py")):
        digest.update(path.name.encode() + b"\0" + path.read_bytes())
    return digest.hexdigest()[:12]


# numba reads NUMBA_CACHE_DIR when it is first imported (by tapecell.estimator._kernels).
_os.environ.setdefault("NUMBA_CACHE_DIR", str(cache_dir() / "numba" / kernel_sources_digest()))

BLAS_THREAD_VARIABLES = ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS")


def one_blas_thread() -> None:
    """Ask for one BLAS thread in this process and its children, unless the environment
    already says how many. It takes effect only before numpy is first imported: the
    command line (``tapecell.cli``) and the benchmarks in ``scripts/`` call it first thing;
    a program that imports the estimator itself decides for itself. The fit's matrices are
    small (a few hundred rows): a product split over threads only waits for them, and far
    longer while another process holds a core (a campaign's workers, the simulator).
    Measured: with the joints' lines in the strip's outline its Jacobian product crossed
    OpenBLAS's threading size, and fits beside one busy process took 1.5-2x as long, their
    times erratic (the answers are the same with any thread count)."""
    for name in BLAS_THREAD_VARIABLES:
        _os.environ.setdefault(name, "1")
