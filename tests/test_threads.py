"""tapecell sets one BLAS thread per process before numpy loads, unless the environment
says otherwise (tapecell/__init__.py: the fit's small products only wait for more)."""
from __future__ import annotations

import os
import subprocess
import sys

CODE = "import tapecell, numpy, os; print(os.environ['OPENBLAS_NUM_THREADS'], os.environ['OMP_NUM_THREADS'])"


def _threads(**env) -> str:
    clean = {k: v for k, v in os.environ.items()
             if k not in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS")}
    r = subprocess.run([sys.executable, "-c", CODE], env={**clean, **env}, capture_output=True, text=True,
                       timeout=120)
    assert r.returncode == 0, r.stderr
    return r.stdout.strip()


def test_one_blas_thread_unless_the_user_chose():
    assert _threads() == "1 1"
    assert _threads(OPENBLAS_NUM_THREADS="2") == "2 1"
