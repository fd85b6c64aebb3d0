"""Parameter sweeps of grasp episodes (``tapecell sweep``): a grid of settings, the same
seeds in every cell of the grid, a ``tape-sweep/1`` summary and a report a person reads.

A parameter is ``cameras`` or ``randomize.NAME`` (any setting of
:mod:`tapecell.sim.randomize`); each takes a list of values, and the grid is every
combination. Each cell of the grid is an ordinary campaign folder,
``DIR/cells/<cell>/results.jsonl`` (resumable as ``tapecell episodes`` is), and all cells'
episodes run together on one backend (one Ray, one process pool). Using the same seeds
in every cell compares the settings on the same tapes.
"""
from __future__ import annotations

import itertools
import json
import re
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, TextIO

import numpy as np

from tapecell.estimator.errors import TapecellError
from tapecell.estimator.io import atomic_write_text

from .episodes import (RESULTS, EpisodeJob, Progress, _end_torn_line, _same_episode, _worker, append_result, done_seeds,
                       load_results, outcome_of, run_jobs, wilson_interval)
from .randomize import CHOICES, NAMES, Randomize, RandomizeError, parse_value

FORMAT = "tape-sweep/1"
SUMMARY = "summary.json"
REPORT = "report.html"
CELLS = "cells"
CAMERAS = (2, 3)


class SweepError(TapecellError):
    """A sweep parameter that cannot be used."""


@dataclass(frozen=True)
class Param:
    """One swept parameter: its name as given (``cameras``, ``randomize.NAME``) and values."""

    name: str
    values: tuple

    @property
    def setting(self) -> str | None:
        """The randomisation setting it sets (None for ``cameras``)."""
        return self.name.split(".", 1)[1] if self.name.startswith("randomize.") else None


def parse_param(text: str) -> Param:
    """``NAME=V1,V2,...``: NAME ``cameras`` or ``randomize.SETTING``; each value a number or,
    for a randomisation setting, a ``lo:hi`` range too (``tape_model`` takes its names)."""
    name, sep, values_text = text.partition("=")
    name = name.strip()
    items = [v.strip() for v in values_text.split(",")]
    if not sep or not name or not values_text.strip() or any(not v for v in items):
        raise SweepError(f"--param {text!r}: expected NAME=V1,V2,... (e.g. cameras=2,3 or randomize.calib_rot_deg=0,0.3)")
    if name == "cameras":
        try:
            values = tuple(int(v) for v in items)
        except ValueError:
            raise SweepError(f"--param {text!r}: cameras must be 2 or 3") from None
        if any(v not in CAMERAS for v in values):
            raise SweepError(f"--param {text!r}: cameras must be 2 or 3")
    elif name.startswith("randomize."):
        setting = name.split(".", 1)[1]
        if setting not in NAMES:
            raise SweepError(f"--param {name}: unknown randomisation setting {setting!r} (known: {', '.join(NAMES)})")
        values = []
        for item in items:
            if setting not in CHOICES and ":" in item and item.count(":") != 1:
                raise SweepError(f"--param {name}: bad value {item!r}")
            try:
                value = parse_value(setting, item, f"--param {name}")
                Randomize().with_settings({setting: value}, f"--param {name}")
            except RandomizeError as e:
                raise SweepError(str(e)) from None
            values.append(value)
        values = tuple(values)
    else:
        raise SweepError(f"--param {name!r}: unknown parameter (cameras or randomize.NAME, NAME one of "
                         f"{', '.join(NAMES)})")
    if len(set(values)) != len(values):
        raise SweepError(f"--param {text!r}: a value is repeated")
    return Param(name, values)


def check_params(params: list[Param]) -> None:
    names = [p.name for p in params]
    for n in set(names):
        if names.count(n) > 1:
            raise SweepError(f"--param {n} is given twice")
    if "cameras" in names and "randomize.cameras" in names:
        raise SweepError("--param cameras and --param randomize.cameras both set the camera count: give one")


def grid(params: list[Param]) -> list[dict[str, Any]]:
    """Every combination of the parameters' values, the first parameter slowest."""
    return [dict(zip([p.name for p in params], combo)) for combo in itertools.product(*[p.values for p in params])]


def value_text(v: Any) -> str:
    if isinstance(v, tuple):
        return f"{value_text(v[0])}:{value_text(v[1])}"
    if isinstance(v, float):
        return f"{v:g}"
    return str(v)


def point_label(point: dict[str, Any]) -> str:
    """``cameras=2 calib_rot_deg=0.3``: a grid cell as people read it."""
    return " ".join(f"{k.removeprefix('randomize.')}={value_text(v)}" for k, v in point.items()) or "default"


def cell_name(point: dict[str, Any]) -> str:
    """A folder name for a grid cell: ``cameras-2_calib_rot_deg-0.3``."""
    parts = [f"{k.removeprefix('randomize.')}-{value_text(v)}" for k, v in point.items()]
    return re.sub(r"[^A-Za-z0-9_.\-]", "_", "_".join(parts)) or "default"


def json_value(v: Any) -> Any:
    """A parameter value in JSON: a range as [lo, hi]."""
    return list(v) if isinstance(v, tuple) else v


@dataclass(frozen=True)
class Cell:
    point: dict
    folder: Path
    cameras: int
    randomize: Randomize


def plan_cells(params: list[Param], out: Path, base: Randomize, cameras: int) -> list[Cell]:
    cells = []
    for point in grid(params):
        settings = {p.setting: point[p.name] for p in params if p.setting is not None}
        cells.append(Cell(point, out / CELLS / cell_name(point), int(point.get("cameras", cameras)),
                          base.with_settings(settings, "--param")))
    return cells


def run_sweep(params: list[Param], n: int, seed: int, out: Path, jobs: int = 1, backend: str = "process",
              address: str | None = None, config: Any = None, base: Randomize | None = None, cameras: int = 2,
              rrd: str | None = "failures", worker: Callable[[EpisodeJob], dict] = _worker,
              progress_stream: TextIO | None = None, settings: dict | None = None) -> dict:
    """Run every grid cell's ``n`` episodes (seeds ``seed .. seed+n-1``, the same in each
    cell; those already in a cell's results.jsonl are skipped), then write
    ``out/summary.json`` and ``out/report.html`` with its plots. Returns the summary."""
    check_params(params)
    base = base or Randomize()
    cells = plan_cells(params, out, base, cameras)
    seeds = list(range(seed, seed + n))
    jobs_list: list[EpisodeJob] = []
    cell_of: dict[int, Cell] = {}
    for cell in cells:
        cell.folder.mkdir(parents=True, exist_ok=True)
        path = cell.folder / RESULTS
        _end_torn_line(path)
        done = done_seeds(load_results(path), cell.cameras)
        for s in seeds:
            if s not in done:
                job = EpisodeJob(s, cell.cameras, cell.folder / f"episode-{s:04d}.rrd" if rrd else None, config,
                                 rrd == "failures", cell.randomize)
                jobs_list.append(job)
                cell_of[id(job)] = cell
    stream = progress_stream or sys.stderr
    total = len(cells) * n
    if len(jobs_list) < total:
        print(f"{total - len(jobs_list)} of {total} episodes already in {out / CELLS}; running {len(jobs_list)}",
              file=stream)
    # Interleave the cells (seed-major), so a partial run covers every cell alike.
    order = {id(c): i for i, c in enumerate(cells)}
    jobs_list.sort(key=lambda j: (j.seed, order[id(cell_of[id(j)])]))
    progress = Progress(len(jobs_list), stream, "sweep")
    t0 = time.perf_counter()
    for job, doc in run_jobs(jobs_list, jobs, backend, address, worker):
        append_result(cell_of[id(job)].folder / RESULTS, doc)
        progress.update(doc)
    wall = time.perf_counter() - t0
    rows = []
    per_cell = []
    for cell in cells:
        by_seed = {r["seed"]: r for r in load_results(cell.folder / RESULTS)
                   if isinstance(r.get("seed"), int) and _same_episode(r, r["seed"], cell.cameras)}
        results = [by_seed[s] for s in seeds if s in by_seed]
        per_cell.append(results)
        rows.append(summary_row(cell, results, out))
    summary = {"format": FORMAT, "rows": rows,
               "settings": {**(settings or {}), "n": n, "seeds": [seed, seed + n - 1], "backend": backend,
                            "jobs": jobs, "cameras": cameras,
                            "randomize": {k: json_value(v) for k, v in base.settings.items()},
                            "params": {p.name: [json_value(v) for v in p.values] for p in params},
                            "wall_s_this_run": round(wall, 2), "episodes_this_run": len(jobs_list)}}
    atomic_write_text(out / SUMMARY, json.dumps(summary, indent=1) + "\n")
    from .report import write_report
    write_report(out, summary, params, cells, per_cell)
    return summary


def summary_row(cell: Cell, results: list[dict], out: Path) -> dict:
    """One ``tape-sweep/1`` row of a grid cell's results."""
    n = len(results)
    k = sum(1 for r in results if outcome_of(r) == "grasped")
    lo, hi = wilson_interval(k, n)
    tips = [float(r["tip_error_mm"]) for r in results if r.get("tip_error_mm") is not None]
    times = [sum((r.get("time_s") or {}).values()) for r in results if r.get("time_s")]
    reasons: dict[str, int] = {}
    for r in results:
        if outcome_of(r) != "grasped":
            key = f"{outcome_of(r)}: {r.get('failure') or '?'}"
            reasons[key] = reasons.get(key, 0) + 1
    return {"params": {k_: json_value(v) for k_, v in cell.point.items()}, "n": n, "success": k,
            "rate": round(k / n, 4) if n else None, "ci95": [round(lo, 4), round(hi, 4)],
            "refused": sum(1 for r in results if outcome_of(r) == "refused"),
            "failed": sum(1 for r in results if outcome_of(r) == "failed"),
            "tip_error_mm": {"median": round(float(np.median(tips)), 3) if tips else None,
                             "p90": round(float(np.percentile(tips, 90)), 3) if tips else None},
            "time_s_per_episode": round(float(np.mean(times)), 3) if times else None,
            "reasons": dict(sorted(reasons.items(), key=lambda kv: -kv[1])),
            "results": str((cell.folder / RESULTS).relative_to(out))}


def format_table(summary: dict) -> str:
    """The summary's rows as a text table."""
    lines = [f"{'cell':<40} {'n':>5} {'grasped':>8} {'95% interval':>15} {'refused':>7} {'failed':>6} "
             f"{'tip med':>7} {'tip p90':>7} {'s/ep':>6}"]
    for row in summary["rows"]:
        tip = row["tip_error_mm"]
        f = (lambda v: "n/a" if v is None else f"{v:.2f}")
        rate = "n/a" if row["rate"] is None else f"{100 * row['rate']:.1f}%"
        lines.append(f"{point_label(row['params']):<40} {row['n']:>5} {rate:>8} "
                     f"{100 * row['ci95'][0]:6.1f}-{100 * row['ci95'][1]:5.1f}% {row['refused']:>7} {row['failed']:>6} "
                     f"{f(tip['median']):>7} {f(tip['p90']):>7} {f(row['time_s_per_episode']):>6}")
    return "\n".join(lines)
