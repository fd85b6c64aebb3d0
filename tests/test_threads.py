"""The command line and the benchmarks ask for one BLAS thread per process before numpy
loads, unless the environment says otherwise (tapecell.one_blas_thread: the fit's small
products only wait for more threads); importing the estimator alone leaves it be."""
from __future__ import annotations

import os
import subprocess
import sys

import tapecell

READ = "import os; print(os.environ.get('OPENBLAS_NUM_THREADS'), os.environ.get('OMP_NUM_THREADS'))"


def _threads(code: str, **env) -> str:
    clean = {k: v for k, v in os.environ.items() if k not in tapecell.BLAS_THREAD_VARIABLES}
    r = subprocess.run([sys.executable, "-c", f"{code}; {READ}"], env={**clean, **env}, capture_output=True,
                       text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    return r.stdout.strip()


def test_one_blas_thread_for_the_command_line_unless_the_user_chose():
    assert _threads("import tapecell.cli") == "1 1"
    assert _threads("import tapecell.cli", OPENBLAS_NUM_THREADS="2") == "2 1"
    assert _threads("import tapecell.estimator") == "None None"
