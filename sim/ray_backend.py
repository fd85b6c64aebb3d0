"""Episodes as Ray tasks (``tapecell episodes --backend ray``): a local Ray started in this
process, bound to the loopback address, or a running cluster (``--address HOST:PORT``).

Each episode is one task (one CPU). The task runs the same worker as the process pool, so
the same seeds give the same results on either backend. A recording is written on the
worker's machine to a temporary file and comes back with the result as bytes: the driver
writes it into the results folder, so a cluster needs no shared file system. The cell file
is loaded by the driver and sent with each task (a cluster's machines need tapecell
installed, not the driver's files; a ``cameras_file`` the cell file names must be readable
at the same path on every machine).

A task whose worker process dies (a crash, the machine lost, killed for memory) is run once
more by Ray (``max_retries=1``); when that dies too, the episode is reported as failed
("worker died") and the campaign goes on. Ray's usage statistics are switched off: nothing
is sent anywhere but to the cluster.

Ray is an optional dependency: ``pip install "tapecell[ray]"``.
"""
from __future__ import annotations

import dataclasses
import ipaddress
import logging
import os
import socket
import sys
import tempfile
from pathlib import Path
from typing import Any, Callable, Iterator

from tapecell.estimator.errors import HardwareError, TapecellError
from tapecell.estimator.io import atomic_write_bytes

from .episodes import MAX_ATTEMPTS, EpisodeJob, worker_died

LOCAL_NODE_IP = "127.0.0.1"
"""The local Ray's address: loopback only (no traffic leaves the machine)."""
CONNECT_TIMEOUT_S = 5.0


class ClusterError(HardwareError):
    """The Ray cluster cannot be reached or stopped answering (exit status 3)."""


def import_ray(loopback: bool = True):
    """The ``ray`` module, or a one-line error saying how to install it.

    ``loopback``: this machine's Ray is to use the loopback address only (a local Ray, or a
    cluster at 127.0.0.1). Ray turns a node address of 127.0.0.1 into the machine's network
    address unless multi-node clusters are switched off (``RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER=0``,
    read when ray is imported, and inherited by the processes Ray starts)."""
    os.environ.setdefault("RAY_USAGE_STATS_ENABLED", "0")   # never send usage statistics anywhere
    if loopback:
        os.environ[LOOPBACK_ENV] = "0"
    elif os.environ.get(LOOPBACK_ENV) == "0":
        del os.environ[LOOPBACK_ENV]                          # set by an earlier local run
    try:
        import ray
    except ImportError:
        raise TapecellError("--backend ray needs Ray, an optional dependency: pip install \"tapecell[ray]\"") from None
    import ray._private.ray_constants as constants

    # Ray may have been imported before the variable was set (a test, a notebook): the
    # constant is read at call time.
    constants.ENABLE_RAY_CLUSTER = not loopback and sys.platform.startswith("linux")
    for name in ("ray._private.authentication.authentication_token_setup", "ray._private.authentication"):
        logging.getLogger(name).setLevel(logging.ERROR)    # "token authentication is enabled" on every start
    return ray


LOOPBACK_ENV = "RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER"


def parse_address(address: str) -> tuple[str, int]:
    """(host, port) of ``HOST:PORT``; a one-line error when it is not one."""
    host, sep, port_text = address.strip().rpartition(":")
    host = host.strip("[]")
    if not sep or not host or not port_text.isdigit() or not 0 < int(port_text) < 65536:
        raise TapecellError(f"--address {address!r}: expected HOST:PORT, e.g. 127.0.0.1:6379 "
                            "(the head node's address printed by 'ray start --head')")
    return host, int(port_text)


def is_loopback(host: str) -> bool:
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


def check_reachable(address: str, timeout_s: float = CONNECT_TIMEOUT_S) -> tuple[str, int]:
    """Open (and close) a TCP connection to the head node's port, so that an address where
    no cluster listens is one clear error within ``timeout_s`` instead of Ray's long retries."""
    host, port = parse_address(address)
    try:
        with socket.create_connection((host, port), timeout=timeout_s):
            pass
    except socket.gaierror:
        raise ClusterError(f"--address {address}: unknown host {host!r}") from None
    except (TimeoutError, socket.timeout):
        raise ClusterError(f"--address {address}: no Ray cluster answered within {timeout_s:g} s") from None
    except OSError as e:
        raise ClusterError(f"--address {address}: cannot reach a Ray cluster there "
                           f"({e.strerror or e}; is 'ray start --head' running?)") from None
    return host, port


def connect(ray, jobs: int, address: str | None) -> None:
    """Start a local Ray of ``jobs`` CPUs on the loopback address, or join the cluster at
    ``address``."""
    quiet = dict(log_to_driver=False, logging_level=logging.WARNING, include_dashboard=False)
    if address is None:
        # "local": always a new Ray of our own, never one found on the machine
        try:
            ray.init(address="local", num_cpus=jobs, _node_ip_address=LOCAL_NODE_IP, namespace="tapecell", **quiet)
        except (ConnectionError, TimeoutError, RuntimeError, ValueError, OSError) as e:
            raise ClusterError(f"--backend ray: could not start a local Ray ({' '.join(str(e).split())[:200]})") \
                from None
        return
    host, _ = check_reachable(address)
    extra = {"_node_ip_address": LOCAL_NODE_IP} if is_loopback(host) else {}
    _use_auth_token_if_any()
    try:
        ray.init(address=address, namespace="tapecell", **extra, **quiet)
    except (ConnectionError, TimeoutError, RuntimeError, ValueError) as e:
        raise ClusterError(f"--address {address}: could not join the Ray cluster ({' '.join(str(e).split())[:200]})") \
            from None


def _use_auth_token_if_any() -> None:
    """Ray 2.60 clusters started by ``ray start`` use token authentication when a token is
    there (``~/.ray/auth_token``, ``RAY_AUTH_TOKEN``); Ray's driver sends it on its own only
    to a cluster it finds itself, not to an explicit address. Send it when we have one (as
    Ray does for ``address="auto"``), unless ``RAY_AUTH_MODE`` says otherwise."""
    if "RAY_AUTH_MODE" in os.environ:
        return
    try:
        from ray._private.authentication.authentication_token_setup import (
            maybe_enable_token_auth_if_token_available)
    except ImportError:       # another Ray version: RAY_AUTH_MODE=token does the same
        return
    maybe_enable_token_auth_if_token_available(warn_if_disabled=False)


def _task(worker: Callable[[EpisodeJob], dict], job: EpisodeJob) -> tuple[dict, bytes | None]:
    """One episode on a Ray worker: the recording goes to a local temporary file and comes
    back as bytes (None when there is none, or it was dropped: a grasped episode with
    ``--rrd failures``)."""
    if job.recording is None:
        return worker(job), None
    with tempfile.TemporaryDirectory(prefix="tapecell-ray-") as tmp:
        local = Path(tmp) / job.recording.name
        doc = worker(dataclasses.replace(job, recording=local))
        data = local.read_bytes() if local.is_file() else None
    return doc, data


def run_on_ray(job_list: list[EpisodeJob], jobs: int, address: str | None,
               worker: Callable[[EpisodeJob], dict]) -> Iterator[tuple[EpisodeJob, dict]]:
    """Run the jobs as Ray tasks, yielding (job, result) as each episode ends (in the order
    they end) after writing its recording, if any, into place."""
    if not job_list:
        return
    ray = import_ray(loopback=address is None or is_loopback(parse_address(address)[0]))
    from tapecell.cell.config import CellConfig, load_cell_config

    # The driver's cell file is read here and sent with the tasks.
    configs: dict[Any, Any] = {}
    for job in job_list:
        if job.config is not None and not isinstance(job.config, CellConfig) and job.config not in configs:
            configs[job.config] = load_cell_config(job.config)
    connect(ray, jobs, address)
    try:
        task = ray.remote(num_cpus=1, max_retries=MAX_ATTEMPTS - 1, retry_exceptions=False)(_task)
        worker_ref = ray.put(worker)
        # Tasks in flight: enough to keep every CPU of the cluster busy, not all of a
        # 10,000-episode campaign at once (ray.wait over every pending task per result
        # would cost the driver O(n^2)).
        limit = max(16, 2 * int(ray.cluster_resources().get("CPU", jobs)))
        queue = list(reversed(job_list))
        pending: dict[Any, EpisodeJob] = {}
        while queue or pending:
            while queue and len(pending) < limit:
                job = queue.pop()
                sent = dataclasses.replace(job, config=configs.get(job.config, job.config))
                pending[task.remote(worker_ref, sent)] = job
            ready, _ = ray.wait(list(pending), num_returns=1)
            for ref in ready:
                job = pending.pop(ref)
                yield job, _collect(ray, ref, job)
    finally:
        ray.shutdown()


def _collect(ray, ref, job: EpisodeJob) -> dict:
    try:
        doc, data = ray.get(ref)
    except ray.exceptions.RayTaskError as e:     # the worker function itself raised
        cause = " ".join(str(getattr(e, "cause", None) or e).split())[:300]
        return {**worker_died(job, cause), "failure": "crash"}
    except ray.exceptions.RayError as e:          # its process or machine died, twice
        return worker_died(job, f"its Ray worker died on each of {MAX_ATTEMPTS} attempts "
                                f"({type(e).__name__})")
    if data is not None and job.recording is not None:
        atomic_write_bytes(job.recording, data)
    return doc
