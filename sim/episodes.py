"""Many sim episodes: parallel processes or Ray tasks, a progress bar, a resumable results
file and a summary.

``DIR/results.jsonl`` gets one `tape-episode/1` line as each episode ends (appended and
flushed, so a crash loses nothing); a rerun skips the seeds already in it.
"""
from __future__ import annotations

import contextlib
import json
import math
import multiprocessing as mp
import os
import sys
import time
from collections import Counter
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Iterable, Iterator, TextIO

import numpy as np

from tapecell.estimator.errors import TapecellError

RESULTS = "results.jsonl"


@dataclass(frozen=True)
class EpisodeJob:
    """What one worker runs: seed, number of cameras, where to write a recording (or None),
    the cell file (None = bundled), and whether to keep the recording only when the episode
    did not grasp (a reviewer usually wants the failures)."""

    seed: int
    cameras: int
    recording: Path | None
    config: Any
    failures_only: bool = False
    randomize: Any = None
    """A :class:`~tapecell.sim.randomize.Randomize` (None: the cell file's table)."""


def load_results(path: Path) -> list[dict[str, Any]]:
    """The episode lines already in ``path``; a torn last line (a crash mid-write) is skipped."""
    if not path.exists():
        return []
    out = []
    for line in path.read_text().splitlines():
        line = line.strip()
        if not line:
            continue
        try:
            doc = json.loads(line)
        except json.JSONDecodeError:
            continue
        if isinstance(doc, dict) and doc.get("format") == "tape-episode/1":
            out.append(doc)
    return out


def append_result(path: Path, doc: dict[str, Any]) -> None:
    """Append one JSON line with a single write and fsync, so lines never interleave."""
    data = (json.dumps(doc) + "\n").encode()
    fd = os.open(path, os.O_WRONLY | os.O_APPEND | os.O_CREAT, 0o666)   # the umask decides
    try:
        os.write(fd, data)
        os.fsync(fd)
    finally:
        os.close(fd)


def _end_torn_line(path: Path) -> None:
    """After a crash mid-write the file may end inside a line: end it, so the next result
    starts on a line of its own (the torn line is skipped when read)."""
    if path.exists() and path.stat().st_size > 0:
        with open(path, "rb") as f:
            f.seek(-1, os.SEEK_END)
            last = f.read(1)
        if last != b"\n":
            with open(path, "ab") as f:
                f.write(b"\n")


def wilson_interval(successes: int, n: int, z: float = 1.959964) -> tuple[float, float]:
    """95 % Wilson score interval of a success rate."""
    if n == 0:
        return (0.0, 1.0)
    p = successes / n
    denom = 1 + z * z / n
    centre = (p + z * z / (2 * n)) / denom
    half = z * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / denom
    return (max(0.0, centre - half), min(1.0, centre + half))


def _percentiles(values: list[float]) -> str:
    if not values:
        return "n/a"
    v = np.asarray(values, float)
    return (f"median {np.median(v):.2f}  p90 {np.percentile(v, 90):.2f}  "
            f"max {v.max():.2f}")


STAGE_OF_REASON = {"estimate rejected": "estimator", "unreachable": "planner", "limits": "planner",
                   "collision": "planner", "missed": "execution", "slipped": "execution",
                   "short lift": "execution", "arm error": "execution"}
BLAME_TIP_ERROR_MM = 4.0
"""A failed grasp whose estimate was off by more than this is blamed on the estimator."""


def blame(result: dict[str, Any]) -> str | None:
    """The stage a failed episode is blamed on: "estimator", "planner", "execution" or "error"."""
    if result.get("success"):
        return None
    tip = result.get("tip_error_mm")
    if tip is not None and tip > BLAME_TIP_ERROR_MM and result.get("failure") in ("missed", "slipped", "unreachable",
                                                                               "collision", "limits"):
        return "estimator"
    return STAGE_OF_REASON.get(result.get("failure") or "", "error")


def outcome_of(result: dict[str, Any]) -> str:
    """"grasped", "refused" or "failed" (results written before ``outcome`` existed: a
    success was grasped, anything else counted as failed)."""
    return result.get("outcome") or ("grasped" if result.get("success") else "failed")


def _rate(k: int, n: int) -> str:
    lo, hi = wilson_interval(k, n)
    return f"{k}/{n} = {100 * k / max(n, 1):.1f} % (95 % interval {100 * lo:.1f}-{100 * hi:.1f} %)"


def summarize(results: list[dict[str, Any]], wall_s: float | None = None) -> str:
    """Grasped, refused (nothing touched the tape: safe) and failed (acted and did not take
    it: the worst outcome), each with a 95 % interval and its reasons; error percentiles;
    timings; the same per camera count."""
    n = len(results)
    lines = [f"episodes {n}"]
    for outcome in ("grasped", "refused", "failed"):
        sub = [r for r in results if outcome_of(r) == outcome]
        line = f"  {outcome:<8} {_rate(len(sub), n)}"
        if outcome != "grasped" and sub:
            reasons = Counter(f"{r.get('failure') or '?'}" + (f" ({r['verdict']})" if r.get("verdict") not in (None, "ok")
                                                              else "") for r in sub)
            line += "   " + ", ".join(f"{k} x{v}" for k, v in reasons.most_common())
        lines.append(line)
    failed = [r for r in results if not r.get("success")]
    if failed:
        stages = Counter(blame(r) for r in failed)
        lines.append("not grasped, blamed on: " + ", ".join(f"{k} x{v}" for k, v in stages.most_common())
                     + f"  (estimator: tip error > {BLAME_TIP_ERROR_MM:g} mm or estimate rejected)")
    tip = [r["tip_error_mm"] for r in results if r.get("tip_error_mm") is not None]
    nrm = [r["normal_error_deg"] for r in results if r.get("normal_error_deg") is not None]
    lines.append(f"tip error mm:     {_percentiles(tip)}")
    lines.append(f"normal error deg: {_percentiles(nrm)}")
    stages: dict[str, list[float]] = {}
    for r in results:
        for k, v in (r.get("time_s") or {}).items():
            stages.setdefault(k, []).append(float(v))
    if stages:
        lines.append("time s (median):  " + "  ".join(f"{k} {np.median(v):.3f}" for k, v in stages.items())
                     + f"  total {np.median([sum(r.get('time_s', {}).values()) for r in results]):.2f}")
    if wall_s is not None and n:
        lines.append(f"wall time {wall_s:.1f} s for this run")
    for cams in sorted({r.get("cameras") for r in results if r.get("cameras")}):
        sub = [r for r in results if r.get("cameras") == cams]
        counts = Counter(outcome_of(r) for r in sub)
        lines.append(f"  {cams} cameras: grasped {_rate(counts['grasped'], len(sub))}, refused {counts['refused']}, "
                     f"failed {counts['failed']}")
    return "\n".join(lines)


def _clock(seconds: float) -> str:
    """``h:mm:ss`` (or ``m:ss``) of a duration."""
    if not math.isfinite(seconds):
        return "--:--"
    s = int(round(seconds))
    h, s = divmod(s, 3600)
    m, s = divmod(s, 60)
    return f"{h}:{m:02d}:{s:02d}" if h else f"{m}:{s:02d}"


class Progress:
    """Progress of a campaign: on a terminal one line redrawn in place (a bar, done/total,
    episodes per second, time left, counts by outcome); otherwise (a log, CI) one plain line
    per episode with the same numbers."""

    def __init__(self, total: int, stream: TextIO = sys.stderr, label: str = ""):
        self.total, self.done, self.stream, self.label = total, 0, stream, label
        self.counts: Counter = Counter()
        self.start = time.perf_counter()
        try:
            self.tty = stream.isatty()
        except (AttributeError, ValueError):
            self.tty = False

    def line(self, doc: dict[str, Any] | None = None) -> str:
        elapsed = time.perf_counter() - self.start
        rate = self.done / elapsed if elapsed > 0 else 0.0
        left = (self.total - self.done) / rate if rate > 0 else math.inf
        counts = f"grasped {self.counts['grasped']} refused {self.counts['refused']} failed {self.counts['failed']}"
        head = f"{self.label} " if self.label else ""
        if self.tty:
            width = 24
            filled = int(width * self.done / max(self.total, 1))
            return (f"{head}[{'#' * filled}{'.' * (width - filled)}] {self.done}/{self.total} "
                    f"{rate:.2f} ep/s  left {_clock(left)}  {counts}")
        what = ""
        if doc is not None:
            what = f"  seed {doc.get('seed')} {outcome_of(doc)}" + (f" ({doc.get('failure')})" if doc.get("failure")
                                                                    else "")
        return (f"{head}{self.done}/{self.total} episodes  {rate:.2f} ep/s  elapsed {_clock(elapsed)}  "
                f"left {_clock(left)}  {counts}{what}")

    def update(self, doc: dict[str, Any]) -> None:
        self.done += 1
        self.counts[outcome_of(doc)] += 1
        msg = self.line(doc)
        if self.tty:
            self.stream.write("\r" + msg.ljust(110)[:200])
            if self.done == self.total:
                self.stream.write("\n")
        else:
            self.stream.write(msg + "\n")
        self.stream.flush()


def _worker(job: EpisodeJob) -> dict[str, Any]:
    from .episode import run_episode_safely
    doc = run_episode_safely(job.seed, job.cameras, job.recording, job.config, job.randomize)
    if job.failures_only and doc.get("success") and job.recording is not None:
        job.recording.unlink(missing_ok=True)
        doc.pop("recording", None)
    return doc


def worker_died(job: EpisodeJob, detail: str) -> dict[str, Any]:
    """The result of an episode whose worker process died twice (a crash of MuJoCo, the GL
    driver, the machine): reported as failed, so a campaign never hangs on it."""
    return {"format": "tape-episode/1", "seed": int(job.seed), "cameras": int(job.cameras), "success": False,
            "outcome": "failed", "verdict": None, "failure": "worker died", "detail": detail,
            "tip_error_mm": None, "normal_error_deg": None, "time_s": {}}


RRD_MODES = ("all", "failures")
BACKENDS = ("process", "ray")
MAX_ATTEMPTS = 2
"""An episode whose worker dies is run once more; a second death is reported."""


def _run_in_processes(job_list: list[EpisodeJob], jobs: int,
                      worker: Callable[[EpisodeJob], dict]) -> Iterator[tuple[EpisodeJob, dict]]:
    """Run the jobs in ``jobs`` spawned processes, yielding (job, result) as each ends.

    At most ``jobs`` episodes are in flight. A worker process that dies (a segfault, the
    OOM killer) breaks the pool and every episode in flight with it; which one caused it is
    not known, so each is run again on its own, where a death is its own. An episode whose
    worker dies ``MAX_ATTEMPTS`` times while it ran alone (on its own, or as the last one in
    the pool) is reported as failed ("worker died"); the others go on."""
    from collections import deque
    from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait
    from concurrent.futures.process import BrokenProcessPool

    # spawn: each worker builds its own MuJoCo renderer (EGL contexts do not survive fork)
    ctx = mp.get_context("spawn")
    queue = deque(job_list)
    solo: deque = deque()
    deaths: Counter = Counter()          # deaths while running alone: certainly its own

    def died(job: EpisodeJob) -> dict | None:
        deaths[id(job)] += 1
        if deaths[id(job)] >= MAX_ATTEMPTS:
            return worker_died(job, f"its worker process died on each of {MAX_ATTEMPTS} attempts")
        solo.append(job)
        return None

    while queue or solo:
        if solo:
            job = solo.popleft()
            with ProcessPoolExecutor(1, mp_context=ctx) as one:
                try:
                    doc = one.submit(worker, job).result()
                except BrokenProcessPool:
                    doc = died(job)
            if doc is not None:
                yield job, doc
            continue
        with ProcessPoolExecutor(jobs, mp_context=ctx, max_tasks_per_child=50) as pool, _stopped_on_exit(pool):
            running: dict[Any, EpisodeJob] = {}
            broken: list[EpisodeJob] = []
            while (queue or running) and not broken:
                pool_broke = False
                while queue and len(running) < jobs:
                    job = queue.popleft()
                    try:
                        running[pool.submit(worker, job)] = job
                    except BrokenProcessPool:
                        # a worker died since the last wait: this job never started
                        queue.appendleft(job)
                        pool_broke = True
                        break
                if pool_broke and not running:
                    break                                  # nothing lost: a new pool runs the queue
                # after a break every future in flight is done (a result or the break)
                done, _ = wait(list(running), return_when="ALL_COMPLETED" if pool_broke else FIRST_COMPLETED)
                for fut in done:
                    job = running.pop(fut)
                    try:
                        doc = fut.result()
                    except BrokenProcessPool:
                        broken.append(job)
                        continue
                    yield job, doc
            if broken:
                broken += list(running.values())      # in flight when the pool broke: died with it
                if len(broken) == 1:                   # it was alone: its own death
                    doc = died(broken[0])
                    if doc is not None:
                        yield broken[0], doc
                else:
                    solo.extend(broken)


@contextlib.contextmanager
def _stopped_on_exit(pool) -> Iterator[None]:
    """On Ctrl-C, SIGTERM or any error inside: cancel the episodes not started and end the
    pool's worker processes at once, instead of waiting for the episodes in flight (which
    are lost, not written: a rerun runs them). Without this a second signal during that wait
    left the command hanging with its workers idle."""
    try:
        yield
    except BaseException:
        processes = list((getattr(pool, "_processes", None) or {}).values())   # shutdown forgets them
        pool.shutdown(wait=False, cancel_futures=True)
        for process in processes:
            process.terminate()
        for process in processes:
            process.join(5.0)
        raise


def run_jobs(job_list: list[EpisodeJob], jobs: int = 1, backend: str = "process", address: str | None = None,
             worker: Callable[[EpisodeJob], dict] = _worker) -> Iterator[tuple[EpisodeJob, dict]]:
    """Run the jobs on ``backend``, yielding (job, result) as each episode ends."""
    if backend not in BACKENDS:
        raise TapecellError(f"--backend must be one of {', '.join(BACKENDS)}, got {backend!r}")
    if address is not None and backend != "ray":
        raise TapecellError("--address needs --backend ray")
    if backend == "ray":
        from .ray_backend import run_on_ray
        return run_on_ray(job_list, jobs, address, worker)
    if jobs == 1 or len(job_list) <= 1:
        return ((job, worker(job)) for job in job_list)
    return _run_in_processes(job_list, jobs, worker)


def _same_episode(doc: dict[str, Any], seed: int, cameras: int) -> bool:
    """Whether result ``doc`` is episode (seed, cameras) of a campaign: its cameras, or any
    when the episode drew its camera count (``randomize.cameras``)."""
    return doc.get("seed") == seed and (doc.get("cameras") == cameras
                                        or "cameras" in (doc.get("randomize") or {}))


def done_seeds(results: list[dict[str, Any]], cameras: int) -> set[int]:
    """The seeds a rerun skips: those with a result, except an episode whose worker died
    (the machine's fault, not the episode's: a rerun runs it again, and its new line
    replaces the old one)."""
    return {r["seed"] for r in results if isinstance(r.get("seed"), int) and _same_episode(r, r["seed"], cameras)
            and r.get("failure") != "worker died"}


def run_episodes(seeds: Iterable[int], cameras: int, out: Path, jobs: int = 1, rrd: str | None = None,
                 config: Any = None, worker: Callable[[EpisodeJob], dict] = _worker,
                 backend: str = "process", address: str | None = None, randomize: Any = None,
                 progress_stream: TextIO | None = None, label: str = "") -> list[dict]:
    """Run the episodes not yet in ``out/results.jsonl``; returns all results for these seeds.

    rrd: "all" writes OUT/episode-NNNN.rrd for every episode, "failures" keeps only those of
    episodes that did not grasp, None none. backend: "process" (a pool of ``jobs`` local
    processes) or "ray" (Ray tasks: a local Ray of ``jobs`` CPUs started in-process and
    bound to 127.0.0.1, or the running cluster at ``address`` HOST:PORT). Each result is
    appended to results.jsonl as its episode ends, whatever the backend; the same seeds give
    the same results on every backend. randomize: a :class:`~tapecell.sim.randomize.Randomize`
    (None: the cell file's ``[randomize]`` table). config: a cell file's path or None."""
    if rrd not in (None,) + RRD_MODES:
        raise TapecellError(f"--rrd must be one of {', '.join(RRD_MODES)}, got {rrd!r}")
    if jobs < 1:
        raise TapecellError(f"--jobs must be 1 or more, got {jobs}")
    if backend not in BACKENDS:
        raise TapecellError(f"--backend must be one of {', '.join(BACKENDS)}, got {backend!r}")
    if address is not None and backend != "ray":
        raise TapecellError("--address needs --backend ray")
    out.mkdir(parents=True, exist_ok=True)
    results_path = out / RESULTS
    seeds = list(seeds)
    _end_torn_line(results_path)
    done = done_seeds(load_results(results_path), cameras)
    todo = [s for s in seeds if s not in done]
    stream = progress_stream or sys.stderr
    if len(todo) < len(seeds):
        print(f"{len(seeds) - len(todo)} of {len(seeds)} episodes already in {results_path}; "
              f"running {len(todo)}", file=stream)
    job_list = [EpisodeJob(s, cameras, out / f"episode-{s:04d}.rrd" if rrd else None, config, rrd == "failures",
                           randomize) for s in todo]
    progress = Progress(len(job_list), stream, label)
    for _, doc in run_jobs(job_list, jobs, backend, address, worker):
        append_result(results_path, doc)
        progress.update(doc)
    by_seed = {r["seed"]: r for r in load_results(results_path)
               if isinstance(r.get("seed"), int) and _same_episode(r, r["seed"], cameras)}
    return [by_seed[s] for s in seeds if s in by_seed]
