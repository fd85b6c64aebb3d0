"""``tapecell sweep``: grasp campaigns over a grid of settings, a ``tape-sweep/1`` summary and
an HTML report with PNG plots.

Every cell of the grid runs the same seeds (a paired comparison: the same tapes under each
setting) into ``DIR/cell-NN/results.jsonl`` (resumable, like ``tapecell episodes``), with
recordings of the episodes that did not grasp. ``DIR/summary.json`` and
``DIR/report.html`` (with ``DIR/plot-*.png``) are written when the grid is done.
"""
from __future__ import annotations

import html
import itertools
import json
import os
import tempfile
from collections import Counter
from pathlib import Path
from typing import Any, Sequence

import cv2
import numpy as np

from tapecell.estimator.errors import TapecellError

from . import plots
from .episodes import outcome_of, run_episodes, wilson_interval
from .randomize import CHOICES, Randomize, RandomizeError, parse_value

FORMAT = "tape-sweep/1"


class SweepError(TapecellError):
    """A sweep that cannot be run as asked."""


def parse_params(items: Sequence[str]) -> list[tuple[str, list[Any]]]:
    """``NAME=V1,V2,...`` strings -> [(name, values)]; NAME is ``cameras`` or
    ``randomize.SETTING``."""
    out: list[tuple[str, list[Any]]] = []
    for item in items:
        name, sep, text = item.partition("=")
        name = name.strip()
        if not sep or not text.strip():
            raise SweepError(f"--param {item!r}: expected NAME=V1,V2,...")
        if any(name == n for n, _ in out):
            raise SweepError(f"--param {name} given twice")
        if name == "cameras":
            try:
                values: list[Any] = [int(v) for v in text.split(",") if v.strip()]
            except ValueError:
                raise SweepError(f"--param cameras={text!r}: cameras are 2 or 3") from None
            if not values or any(v not in (2, 3) for v in values):
                raise SweepError(f"--param cameras={text!r}: cameras are 2 or 3")
        elif name.startswith("randomize."):
            setting = name.split(".", 1)[1]
            values = [v.strip() for v in text.split(",") if v.strip()]
            try:
                values = [parse_value(setting, v, "--param") if setting not in CHOICES else v for v in values]
                for v in values:   # each value must be a valid setting on its own
                    Randomize().with_overrides([f"{setting}={_text(v)}"], "--param")
            except RandomizeError as e:
                raise SweepError(str(e)) from None
        else:
            raise SweepError(f"--param {name!r}: sweepable are cameras and randomize.NAME")
        if len(set(map(str, values))) != len(values):
            raise SweepError(f"--param {name}: a value is repeated")
        out.append((name, values))
    return out


def _text(v: Any) -> str:
    return f"{v[0]}:{v[1]}" if isinstance(v, tuple) else str(v)


def grid(params: list[tuple[str, list[Any]]]) -> list[dict[str, Any]]:
    names = [n for n, _ in params]
    return [dict(zip(names, combo)) for combo in itertools.product(*[vs for _, vs in params])] or [{}]


def row_of(params: dict[str, Any], results: list[dict[str, Any]], cell_dir: str) -> dict[str, Any]:
    """One ``tape-sweep/1`` row from a cell's episode results."""
    n = len(results)
    outcomes = Counter(outcome_of(r) for r in results)
    lo, hi = wilson_interval(outcomes["grasped"], n)
    tips = [r["tip_error_mm"] for r in results if r.get("tip_error_mm") is not None]
    totals = [sum((r.get("time_s") or {}).values()) for r in results]
    reasons = Counter(r.get("failure") or "?" for r in results if not r.get("success"))
    return {"params": {k: (list(v) if isinstance(v, tuple) else v) for k, v in params.items()},
            "n": n, "success": outcomes["grasped"], "rate": round(outcomes["grasped"] / max(n, 1), 4),
            "ci95": [round(lo, 4), round(hi, 4)], "refused": outcomes["refused"], "failed": outcomes["failed"],
            "tip_error_mm": {"median": round(float(np.median(tips)), 3) if tips else None,
                             "p90": round(float(np.percentile(tips, 90)), 3) if tips else None},
            "time_s_per_episode": round(float(np.median(totals)), 3) if totals else None,
            "failure_reasons": dict(reasons), "dir": cell_dir,
            "recordings": sorted(f"{cell_dir}/{r['recording']}" for r in results if r.get("recording"))}


def run_sweep(params: list[tuple[str, list[Any]]], n: int, seed: int, out: Path, jobs: int = 1,
              cameras: int = 2, config: Path | None = None, base: Randomize | None = None,
              backend: str = "process", address: str | None = None) -> dict[str, Any]:
    """Run every cell of the grid (``n`` episodes each, seeds seed..seed+n-1) and write the
    summary and the report; returns the summary."""
    base = base or Randomize()
    out.mkdir(parents=True, exist_ok=True)
    rows, tips = [], []
    cells = grid(params)
    for k, cell in enumerate(cells):
        label = ", ".join(f"{name}={_text(v)}" for name, v in cell.items()) or "defaults"
        print(f"sweep cell {k + 1}/{len(cells)}: {label}", flush=True)
        overrides = [f"{name.split('.', 1)[1]}={_text(v)}" for name, v in cell.items() if name.startswith("randomize.")]
        randomize = base.with_overrides(overrides, "--param")
        cams = int(cell.get("cameras", cameras))
        cell_dir = f"cell-{k:02d}"
        results = run_episodes(range(seed, seed + n), cams, out / cell_dir, jobs, "failures", config,
                               backend=backend, address=address, randomize=randomize)
        rows.append(row_of(cell, results, cell_dir))
        tips.append([r.get("tip_error_mm") for r in results])
    summary = {"format": FORMAT, "seeds": [seed, seed + n - 1], "backend": backend,
               "base_randomize": {k: (list(v) if isinstance(v, tuple) else v) for k, v in base.settings.items()},
               "rows": rows}
    _write_atomic(out / "summary.json", (json.dumps(summary, indent=1) + "\n").encode())
    write_report(summary, tips, out)
    return summary


def _write_atomic(path: Path, data: bytes) -> None:
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(data)
        os.chmod(tmp, 0o666 & ~_umask())
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


def _png(path: Path, img: np.ndarray) -> None:
    ok, buf = cv2.imencode(".png", img)
    if not ok:
        raise SweepError(f"{path}: cannot encode the plot")
    _write_atomic(path, buf.tobytes())


def write_report(summary: dict[str, Any], tips: list[list[Any]], out: Path) -> None:
    """``out/report.html`` and its ``plot-*.png``: success rate with its interval per cell and
    per value of each parameter, tip errors per cell, failure reasons, settings, and links
    to the failures' recordings."""
    rows = summary["rows"]
    labels = [", ".join(f"{k.split('.')[-1]}={v}" for k, v in r["params"].items()) or "defaults" for r in rows]
    figures = [("plot-cells.png", plots.rates_with_intervals("success rate per cell (95 % interval)", labels,
                                                             [r["rate"] for r in rows], [r["ci95"] for r in rows]))]
    names = list(rows[0]["params"]) if rows else []
    for name in names:
        values = sorted({json.dumps(r["params"][name]) for r in rows})
        k = [sum(r["success"] for r in rows if json.dumps(r["params"][name]) == v) for v in values]
        m = [sum(r["n"] for r in rows if json.dumps(r["params"][name]) == v) for v in values]
        figures.append((f"plot-{name.replace('.', '-')}.png", plots.rates_with_intervals(
            f"success rate against {name} (all other settings pooled)", [json.loads(v).__repr__() for v in values],
            [a / max(b, 1) for a, b in zip(k, m)], [wilson_interval(a, b) for a, b in zip(k, m)])))
    figures.append(("plot-tip-error.png", plots.dot_strips("tip error per cell [mm]", labels, tips, "mm")))
    reasons: Counter = Counter()
    for r in rows:
        reasons.update(r["failure_reasons"])
    figures.append(("plot-failures.png", plots.bars("why episodes did not grasp (all cells)", dict(reasons))))
    for name, img in figures:
        _png(out / name, img)
    e = html.escape
    links = [" ".join('<a href="%s">%s</a>' % (e(p), e(Path(p).name)) for p in r["recordings"]) or "-" for r in rows]
    reason_text = [", ".join(f"{k} x{v}" for k, v in r["failure_reasons"].items()) for r in rows]
    table = "".join(
        f"<tr><td>{e(label)}</td><td>{r['n']}</td><td>{100 * r['rate']:.1f} %</td>"
        f"<td>{100 * r['ci95'][0]:.1f}-{100 * r['ci95'][1]:.1f} %</td><td>{r['refused']}</td><td>{r['failed']}</td>"
        f"<td>{r['tip_error_mm']['median']}</td><td>{r['tip_error_mm']['p90']}</td><td>{r['time_s_per_episode']}</td>"
        f"<td>{e(why)}</td><td>{link}</td></tr>"
        for label, r, why, link in zip(labels, rows, reason_text, links))
    page = f"""<!doctype html>
<html><head><meta charset="utf-8"><title>tapecell sweep</title>
<style>body{{font-family:sans-serif;margin:2em;max-width:1100px}} table{{border-collapse:collapse}}
td,th{{border:1px solid #ccc;padding:4px 8px;text-align:left}} img{{max-width:100%;margin:1em 0}}</style></head>
<body><h1>Grasp sweep</h1>
<p>Seeds {summary['seeds'][0]}-{summary['seeds'][1]} in every cell (the same tapes under each setting),
backend {e(summary['backend'])}. Base randomisation: {e(json.dumps(summary['base_randomize']))}.
Outcomes: <b>grasped</b>; <b>refused</b> (nothing touched the tape: safe); <b>failed</b> (it acted and did not
take the tape: the worst outcome). Intervals are 95 % Wilson intervals. Recordings (rerun .rrd) are kept for
the episodes that did not grasp.</p>
<h2>Cells</h2>
<table><tr><th>settings</th><th>n</th><th>success</th><th>95 % interval</th><th>refused</th><th>failed</th>
<th>tip error median [mm]</th><th>p90 [mm]</th><th>s / episode</th><th>reasons</th><th>recordings</th></tr>
{table}</table>
<h2>Plots</h2>
{''.join(f'<img src="{name}" alt="{name}">' for name, _ in figures)}
<p>Data: <a href="summary.json">summary.json</a> (format {FORMAT}); per-episode results in each cell's
results.jsonl.</p></body></html>
"""
    _write_atomic(out / "report.html", page.encode())
