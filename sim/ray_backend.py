"""Episodes as Ray tasks (the optional extra ``tapecell[ray]``).

``run_on_ray`` starts a local Ray in-process (``jobs`` CPUs, every service bound to
127.0.0.1, no dashboard) or joins the cluster at ``address`` (HOST:PORT of a head started
with ``ray start --head``; its machines have tapecell installed). Each episode is one task
of one CPU; results are yielded as tasks finish. A worker process that dies loses only its
episode: Ray runs that task once more (``max_retries=1``), and if it dies again the
episode is reported as failed ("worker died"). Every episode draws everything from its
seed, so the results are the same as the process pool's.
"""
from __future__ import annotations

import os
from typing import Any, Callable, Iterator

from tapecell.estimator.errors import TapecellError

LOOPBACK = "127.0.0.1"
MAX_RETRIES = 1
"""A task whose worker process died is run this many more times before it is reported."""


class RayBackendError(TapecellError):
    """Ray is missing or its cluster cannot be reached."""


def _is_loopback(address: str | None) -> bool:
    return address is None or address.split(":")[0] in ("127.0.0.1", "localhost")


def _import_ray(loopback: bool):
    if loopback:
        # Ray turns 127.0.0.1 into the machine's network address and serves on it unless
        # clustering across machines is off (this variable, read when ray is imported):
        # then every Ray service listens on the loopback address only.
        os.environ.setdefault("RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER", "0")
    try:
        import ray
    except ImportError:
        raise RayBackendError('--backend ray needs Ray: pip install "tapecell[ray]"') from None
    return ray


def start(jobs: int, address: str | None):
    """Connect to Ray (see the module's text); returns the ray module. A Ray already
    initialised in this process (a test's cluster) is used as it is."""
    ray = _import_ray(_is_loopback(address))
    if ray.is_initialized():
        return ray
    os.environ.setdefault("RAY_USAGE_STATS_ENABLED", "0")   # no usage reports: loopback only
    try:
        if address:
            ray.init(address=address, log_to_driver=False, configure_logging=False)
        else:
            ray.init(num_cpus=jobs, include_dashboard=False, _node_ip_address=LOOPBACK,
                     log_to_driver=False, configure_logging=False)
    except (ConnectionError, RuntimeError, ValueError) as e:
        where = f"the Ray cluster at {address}" if address else "a local Ray"
        raise RayBackendError(f"cannot start or reach {where}: {str(e).splitlines()[0] if str(e) else e}") from None
    return ray


def run_on_ray(jobs_list: list, jobs: int, address: str | None,
               worker: Callable[[Any], dict]) -> Iterator[dict[str, Any]]:
    """Run ``worker(job)`` for every job as a Ray task; yield each result as it finishes."""
    if not jobs_list:
        return
    from .episode import failed_episode

    ray = start(jobs, address)
    task = ray.remote(num_cpus=1, max_retries=MAX_RETRIES)(worker)
    pending = {task.remote(job): job for job in jobs_list}
    while pending:
        done, _ = ray.wait(list(pending), num_returns=1)
        for ref in done:
            job = pending.pop(ref)
            try:
                yield ray.get(ref)
            except (ray.exceptions.WorkerCrashedError, ray.exceptions.NodeDiedError,
                    ray.exceptions.RayTaskError, ray.exceptions.TaskCancelledError) as e:
                yield failed_episode(job.seed, job.cameras, "worker died",
                                     f"{type(e).__name__} after {MAX_RETRIES} retry: {_last_line(e)}")


def _last_line(e: BaseException) -> str:
    """The last non-empty line of an error's text (a Ray task error's is its cause)."""
    lines = [line.strip() for line in str(e).splitlines() if line.strip()]
    return lines[-1] if lines else type(e).__name__
