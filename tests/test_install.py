"""The README's Quick start leaves a working ``tapecell``: install, run (the kernels compile
and are cached), reinstall editable, run again from another folder (issue 11: numba's
cache in the installed package's folder outlived the uninstall and shadowed the editable
install as a namespace package).

Slow (one cold compile of the kernels, ~20 s): marked ``slow`` so it can be deselected
locally (``-m "not slow"``); CI runs it. Cheap otherwise: a venv without pip whose
site-packages sees this interpreter's dependencies through a .pth file (everything but
tapecell itself), and ``pip --python VENV install --no-deps`` (the build backend comes from the
index, as in the Quick start).
"""
from __future__ import annotations

import os
import shutil
import subprocess
import sys
import sysconfig
from pathlib import Path

import pytest

import tapecell
from tapecell.estimator.capture import save_capture
from tapecell.estimator.synthetic import SyntheticOptions, make_capture

SOURCE = Path(tapecell.__file__).resolve().parent
pytestmark = pytest.mark.slow


def _run(cmd, **kw) -> subprocess.CompletedProcess:
    r = subprocess.run([str(c) for c in cmd], capture_output=True, text=True, timeout=600, **kw)
    assert r.returncode == 0, f"{cmd}: exit {r.returncode}\n{r.stdout[-2000:]}\n{r.stderr[-3000:]}"
    return r


def _dependencies(dest: Path) -> Path:
    """A folder of links to everything in this interpreter's site-packages except tapecell
    (and its editable finder): the heavy dependencies, without installing them again."""
    dest.mkdir()
    for lib in {sysconfig.get_paths()["purelib"], sysconfig.get_paths()["platlib"]}:
        for entry in Path(lib).iterdir():
            if "tapecell" in entry.name.lower() or (dest / entry.name).exists():
                continue
            (dest / entry.name).symlink_to(entry)
    return dest


def _installed_files_not_in_record(site: Path) -> list[str]:
    record = next(site.glob("tapecell-*.dist-info")) / "RECORD"
    listed = {line.split(",")[0] for line in record.read_text().splitlines() if line}
    return sorted(str(p.relative_to(site)) for p in (site / "tapecell").rglob("*")
                  if p.is_file() and str(p.relative_to(site)) not in listed)


@pytest.mark.skipif(not (SOURCE / "pyproject.toml").is_file(), reason="needs tapecell's source tree")
def test_install_run_reinstall_editable_run_elsewhere(tmp_path):
    src = tmp_path / "src"
    shutil.copytree(SOURCE, src, ignore=shutil.ignore_patterns(".git", "__pycache__", "*.egg-info", "build",
                                                               ".pytest_cache", "*.rrd"))
    venv = tmp_path / "venv"
    _run([sys.executable, "-m", "venv", "--without-pip", venv])
    py = venv / "bin" / "python"
    site = Path(_run([py, "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"]).stdout.strip())
    (site / "_tapecell_test_dependencies.pth").write_text(f"{_dependencies(tmp_path / 'deps')}\n")
    pip = [sys.executable, "-m", "pip", "--python", py, "install", "--no-deps",
           "--disable-pip-version-check", "-q"]

    capture = save_capture(make_capture(20031, SyntheticOptions(kind="chain", cameras=2)), tmp_path / "cap")
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    env = {k: v for k, v in os.environ.items() if k not in ("NUMBA_CACHE_DIR", "PYTHONPATH")}
    env["XDG_CACHE_HOME"] = str(tmp_path / "cache")
    tapecell_cmd = venv / "bin" / "tapecell"

    # 1. pip install . && run: the kernels compile, their cache goes to the user's cache folder.
    _run(pip + [src])
    _run([tapecell_cmd, "estimate", capture], cwd=elsewhere, env=env)
    assert list((tmp_path / "cache" / "tapecell" / "numba").rglob("*.nbi")), "no kernel cache in XDG_CACHE_HOME"
    assert _installed_files_not_in_record(site) == []          # nothing written into the installed package

    # 2. pip install -e . && run again from another folder.
    _run(pip + ["-e", src])
    assert not (site / "tapecell").exists(), "the uninstall left a tapecell folder in site-packages"
    r = _run([py, "-c", "import tapecell, tapecell.estimator; from tapecell.estimator import estimate; "
                        "print(tapecell.__file__)"], cwd=elsewhere, env=env)
    assert Path(r.stdout.strip()).resolve() == (src / "__init__.py").resolve()
    r = subprocess.run([str(tapecell_cmd), "estimate", str(tmp_path / "no-such-capture")], cwd=elsewhere, env=env,
                       capture_output=True, text=True, timeout=300)
    assert r.returncode == 2 and "capture directory not found" in r.stderr, r.stderr   # got past the imports
    assert _run([tapecell_cmd, "--version"], cwd=elsewhere, env=env).stdout.strip() == f"tapecell {tapecell.__version__}"
