"""The sweep's report: ``DIR/report.html`` and its plots in ``DIR/plots/`` (PNG).

The plots are drawn with OpenCV (a dependency already), not matplotlib: plain axes, points
with error bars, box plots and stacked bars, labelled with ``cv2.putText``.

- ``rate_<param>.png``: success rate with its 95 % (Wilson) interval against each swept
  parameter, one series per combination of the other parameters;
- ``tip_error.png``: the tip error of every episode per grid cell (box: quartiles, whiskers:
  10th-90th percentile, dots: episodes);
- ``reasons.png``: why episodes were not grasped, per grid cell.
"""
from __future__ import annotations

import datetime
import html
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from tapecell.estimator.io import atomic_write_bytes, atomic_write_text

from .episodes import outcome_of

PLOTS = "plots"
FONT = cv2.FONT_HERSHEY_SIMPLEX
INK = (40, 40, 40)
GRID = (225, 225, 225)
PALETTE = [(180, 119, 31), (14, 127, 255), (44, 160, 44), (40, 39, 214), (189, 103, 148), (75, 86, 140),
           (194, 119, 227), (127, 127, 127), (34, 189, 188), (207, 190, 23)]   # BGR (tab10)


def _text_size(text: str, scale: float = 0.45, thickness: int = 1) -> tuple[int, int]:
    (w, h), _ = cv2.getTextSize(text, FONT, scale, thickness)
    return w, h


def _put(img: np.ndarray, text: str, x: float, y: float, scale: float = 0.45, color=INK, align: str = "left",
         valign: str = "baseline", thickness: int = 1) -> None:
    w, h = _text_size(text, scale, thickness)
    if align == "center":
        x -= w / 2
    elif align == "right":
        x -= w
    if valign == "middle":
        y += h / 2
    elif valign == "top":
        y += h
    cv2.putText(img, text, (int(round(x)), int(round(y))), FONT, scale, color, thickness, cv2.LINE_AA)


def _ticks(lo: float, hi: float, n: int = 5) -> list[float]:
    """Round tick values covering [lo, hi]."""
    span = max(hi - lo, 1e-9)
    raw = span / n
    mag = 10 ** np.floor(np.log10(raw))
    step = min((m * mag for m in (1, 2, 2.5, 5, 10) if m * mag >= raw), default=10 * mag)
    first = np.ceil(lo / step) * step
    return [float(v) for v in np.arange(first, hi + step * 1e-6, step)]


def _fmt(v: float) -> str:
    return f"{v:g}" if abs(v) >= 0.01 or v == 0 else f"{v:.1e}"


class Axes:
    """A white canvas with a plot area; maps data to pixels."""

    def __init__(self, width: int, height: int, left: int, right: int, top: int, bottom: int, title: str):
        self.img = np.full((height, width, 3), 255, np.uint8)
        self.x0, self.x1, self.y0, self.y1 = left, width - right, top, height - bottom
        _put(self.img, title, width / 2, 22, 0.6, align="center", thickness=1)

    def frame(self) -> None:
        cv2.rectangle(self.img, (self.x0, self.y0), (self.x1, self.y1), INK, 1)

    def yaxis(self, lo: float, hi: float, label: str, ticks: list[float], fmt=_fmt) -> None:
        self.ylo, self.yhi = lo, hi
        for t in ticks:
            y = self.py(t)
            cv2.line(self.img, (self.x0, y), (self.x1, y), GRID, 1)
            cv2.line(self.img, (self.x0 - 4, y), (self.x0, y), INK, 1)
            _put(self.img, fmt(t), self.x0 - 7, y, 0.4, align="right", valign="middle")
        w, h = _text_size(label, 0.45)
        tmp = np.full((h + 8, w + 4, 3), 255, np.uint8)
        _put(tmp, label, 2, h + 2, 0.45)
        rot = cv2.rotate(tmp, cv2.ROTATE_90_COUNTERCLOCKWISE)
        yc = (self.y0 + self.y1) // 2 - rot.shape[0] // 2
        yc = max(0, min(self.img.shape[0] - rot.shape[0], yc))
        self.img[yc:yc + rot.shape[0], 4:4 + rot.shape[1]] = np.minimum(self.img[yc:yc + rot.shape[0], 4:4 + rot.shape[1]], rot)

    def xaxis(self, lo: float, hi: float, label: str, ticks: list[float], fmt=_fmt) -> None:
        self.xlo, self.xhi = lo, hi
        for t in ticks:
            x = self.px(t)
            cv2.line(self.img, (x, self.y0), (x, self.y1), GRID, 1)
            cv2.line(self.img, (x, self.y1), (x, self.y1 + 4), INK, 1)
            _put(self.img, fmt(t), x, self.y1 + 8, 0.4, align="center", valign="top")
        _put(self.img, label, (self.x0 + self.x1) / 2, self.y1 + 40, 0.45, align="center")

    def px(self, v: float) -> int:
        return int(round(self.x0 + (v - self.xlo) / (self.xhi - self.xlo) * (self.x1 - self.x0)))

    def py(self, v: float) -> int:
        return int(round(self.y1 - (v - self.ylo) / (self.yhi - self.ylo) * (self.y1 - self.y0)))

    def legend(self, items: list[tuple[str, tuple]], x: int | None = None, y: int | None = None) -> None:
        if not items:
            return
        w = max(_text_size(t, 0.4)[0] for t, _ in items) + 30
        h = 18 * len(items) + 8
        x = self.x1 - w - 6 if x is None else x
        y = self.y0 + 6 if y is None else y
        cv2.rectangle(self.img, (x, y), (x + w, y + h), (255, 255, 255), -1)
        cv2.rectangle(self.img, (x, y), (x + w, y + h), (190, 190, 190), 1)
        for i, (text, color) in enumerate(items):
            cy = y + 13 + 18 * i
            cv2.rectangle(self.img, (x + 6, cy - 5), (x + 18, cy + 5), color, -1)
            _put(self.img, text, x + 24, cy, 0.4, valign="middle")

    def png(self) -> bytes:
        ok, buf = cv2.imencode(".png", self.img)
        assert ok
        return buf.tobytes()


def _label(point: dict[str, Any]) -> str:
    from .sweep import point_label
    return point_label(point)


def rate_plot(param, rows: list[dict]) -> bytes:
    """Success rate with its 95 % interval against ``param``'s values; one series per
    combination of the other parameters."""
    from .sweep import json_value, value_text

    values = [json_value(v) for v in param.values]
    others: list[dict] = []
    for row in rows:
        rest = {k: v for k, v in row["params"].items() if k != param.name}
        if rest not in others:
            others.append(rest)
    ax = Axes(720, 420, 70, 20, 40, 60, f"success rate against {param.name.removeprefix('randomize.')}")
    ax.yaxis(0.0, 1.0, "success rate (95 % interval)", [0, 0.2, 0.4, 0.6, 0.8, 1.0],
             fmt=lambda v: f"{100 * v:.0f}%")
    n = len(values)
    ax.xlo, ax.xhi = -0.5, n - 0.5
    for i, v in enumerate(param.values):
        x = ax.px(i)
        cv2.line(ax.img, (x, ax.y1), (x, ax.y1 + 4), INK, 1)
        _put(ax.img, value_text(v), x, ax.y1 + 8, 0.45, align="center", valign="top")
    _put(ax.img, param.name.removeprefix("randomize."), (ax.x0 + ax.x1) / 2, ax.img.shape[0] - 10, 0.45,
         align="center")
    width = 0.5
    legend = []
    for s, rest in enumerate(others):
        color = PALETTE[s % len(PALETTE)]
        offset = (s - (len(others) - 1) / 2) * (width / max(len(others), 1)) if len(others) > 1 else 0.0
        pts = []
        for i, v in enumerate(values):
            row = next((r for r in rows if r["params"].get(param.name) == v
                        and {k: w for k, w in r["params"].items() if k != param.name} == rest), None)
            if row is None or row["rate"] is None:
                continue
            x = ax.px(i + offset)
            lo, hi = row["ci95"]
            cv2.line(ax.img, (x, ax.py(lo)), (x, ax.py(hi)), color, 2, cv2.LINE_AA)
            for yv in (lo, hi):
                cv2.line(ax.img, (x - 6, ax.py(yv)), (x + 6, ax.py(yv)), color, 2, cv2.LINE_AA)
            pts.append((x, ax.py(row["rate"])))
            _put(ax.img, f"{row['success']}/{row['n']}", x + 8, ax.py(row["rate"]) - 6, 0.38, color=color)
        for a, b in zip(pts, pts[1:]):
            cv2.line(ax.img, a, b, color, 1, cv2.LINE_AA)
        for p in pts:
            cv2.circle(ax.img, p, 5, color, -1, cv2.LINE_AA)
        if rest:
            legend.append((_label(rest), color))
    ax.frame()
    ax.legend(legend, y=ax.y1 - 18 * len(legend) - 14)
    return ax.png()


def tip_error_plot(rows: list[dict], per_cell: list[list[dict]]) -> bytes:
    """Per grid cell, the tip error of each episode: box (quartiles), whiskers (10th-90th
    percentile), median bar and the episodes as dots; beyond the axis, a count at its end."""
    labels = [_label(r["params"]) for r in rows]
    left = max([_text_size(t, 0.42)[0] for t in labels] + [60]) + 18
    row_h = 34
    height = 90 + row_h * len(rows)
    all_tips = [float(r["tip_error_mm"]) for res in per_cell for r in res if r.get("tip_error_mm") is not None]
    hi = max(2.0, float(np.percentile(all_tips, 95)) * 1.15) if all_tips else 5.0
    hi = min(hi, 50.0)
    ax = Axes(max(720, left + 480), height, left, 25, 40, 50, "tip error of every episode (estimate vs truth)")
    ax.xaxis(0.0, hi, "tip error [mm]  (box: quartiles, whiskers: 10-90 %, dots: episodes)", _ticks(0.0, hi))
    ax.ylo, ax.yhi = len(rows) - 0.5, -0.5
    rng = np.random.default_rng(0)      # fixed jitter
    for i, (label, res) in enumerate(zip(labels, per_cell)):
        y = ax.py(i)
        _put(ax.img, label, ax.x0 - 8, y, 0.42, align="right", valign="middle")
        tips = np.array([float(r["tip_error_mm"]) for r in res if r.get("tip_error_mm") is not None])
        color = PALETTE[i % len(PALETTE)]
        if len(tips) == 0:
            _put(ax.img, "no estimate", ax.x0 + 8, y, 0.4, color=(120, 120, 120), valign="middle")
            continue
        q10, q25, q50, q75, q90 = np.percentile(tips, [10, 25, 50, 75, 90])
        cl = lambda v: ax.px(min(v, hi))  # noqa: E731
        cv2.line(ax.img, (cl(q10), y), (cl(q90), y), INK, 1, cv2.LINE_AA)
        for q in (q10, q90):
            cv2.line(ax.img, (cl(q), y - 6), (cl(q), y + 6), INK, 1)
        cv2.rectangle(ax.img, (cl(q25), y - 10), (max(cl(q75), cl(q25) + 1), y + 10), color, 1)
        cv2.line(ax.img, (cl(q50), y - 10), (cl(q50), y + 10), color, 2)
        over = 0
        for t, j in zip(tips, rng.uniform(-8, 8, len(tips))):
            if t > hi:
                over += 1
                continue
            cv2.circle(ax.img, (ax.px(t), int(y + j)), 2, color, -1, cv2.LINE_AA)
        if over:
            _put(ax.img, f"{over} >", ax.x1 - 4, y - 12, 0.38, color=(40, 39, 214), align="right")
    ax.frame()
    return ax.png()


def reasons_plot(rows: list[dict], per_cell: list[list[dict]]) -> bytes:
    """Per grid cell, the episodes not grasped, stacked by reason (refused / failed: why)."""
    labels = [_label(r["params"]) for r in rows]
    reasons: list[str] = []
    counts = []
    for res in per_cell:
        c: dict[str, int] = {}
        for r in res:
            if outcome_of(r) != "grasped":
                key = f"{outcome_of(r)}: {r.get('failure') or '?'}" + (
                    f" ({r['verdict']})" if r.get("verdict") not in (None, "ok") else "")
                c[key] = c.get(key, 0) + 1
                if key not in reasons:
                    reasons.append(key)
        counts.append(c)
    reasons.sort(key=lambda k: (not k.startswith("failed"), k))
    left = max([_text_size(t, 0.42)[0] for t in labels] + [60]) + 18
    row_h = 30
    legend_h = 18 * len(reasons) + 12
    height = 100 + row_h * len(rows) + legend_h
    n_max = max([sum(c.values()) for c in counts] + [1])
    ax = Axes(max(720, left + 480), height, left, 25, 40, 62 + legend_h, "episodes not grasped, by reason")
    ax.xaxis(0.0, n_max * 1.05, "episodes", [t for t in _ticks(0.0, n_max * 1.05) if float(t).is_integer()],
             fmt=lambda v: f"{v:.0f}")
    ax.ylo, ax.yhi = len(rows) - 0.5, -0.5
    # failures (acted, not taken) in warm colours, refusals (safe) in cool ones
    warm = [(40, 39, 214), (14, 127, 255), (34, 189, 188), (75, 86, 140), (194, 119, 227)]
    cool = [(189, 103, 148), (180, 119, 31), (207, 190, 23), (44, 160, 44), (127, 127, 127)]
    failed = [k for k in reasons if k.startswith("failed")]
    other = [k for k in reasons if not k.startswith("failed")]
    colors = {k: warm[i % len(warm)] for i, k in enumerate(failed)}
    colors.update({k: cool[i % len(cool)] for i, k in enumerate(other)})
    for i, (label, c, row) in enumerate(zip(labels, counts, rows)):
        y = ax.py(i)
        _put(ax.img, label, ax.x0 - 8, y, 0.42, align="right", valign="middle")
        x = 0
        for k in reasons:
            if c.get(k):
                cv2.rectangle(ax.img, (ax.px(x), y - 9), (ax.px(x + c[k]), y + 9), colors[k], -1)
                x += c[k]
        _put(ax.img, f"{x} of {row['n']}" if x else f"none of {row['n']}", ax.px(x) + 6, y, 0.38, valign="middle")
    ax.frame()
    ax.legend([(k, colors[k]) for k in reasons], x=ax.x0, y=ax.y1 + 52)
    return ax.png()


def write_report(out: Path, summary: dict, params, cells, per_cell: list[list[dict]]) -> Path:
    """Write the plots and ``out/report.html``; returns the report's path."""
    rows = summary["rows"]
    plots: list[tuple[str, str]] = []
    for p in params:
        name = f"rate_{p.name.removeprefix('randomize.')}.png"
        atomic_write_bytes(out / PLOTS / name, rate_plot(p, rows))
        plots.append((name, f"Success rate against {p.name}"))
    atomic_write_bytes(out / PLOTS / "tip_error.png", tip_error_plot(rows, per_cell))
    plots.append(("tip_error.png", "Tip error distributions"))
    atomic_write_bytes(out / PLOTS / "reasons.png", reasons_plot(rows, per_cell))
    plots.append(("reasons.png", "Why episodes were not grasped"))
    atomic_write_text(out / "report.html", _html(out, summary, plots, cells, per_cell))
    return out / "report.html"


def _html(out: Path, summary: dict, plots, cells, per_cell) -> str:
    e = html.escape
    s = summary["settings"]
    rows = summary["rows"]

    def num(v, f="{:.2f}"):
        return "n/a" if v is None else f.format(v)

    table = []
    for row in rows:
        tip = row["tip_error_mm"]
        table.append(
            f"<tr><td>{e(_label(row['params']))}</td><td>{row['n']}</td><td>{row['success']}</td>"
            f"<td>{num(row['rate'] * 100 if row['rate'] is not None else None, '{:.1f} %')}</td>"
            f"<td>{100 * row['ci95'][0]:.1f}&ndash;{100 * row['ci95'][1]:.1f} %</td>"
            f"<td>{row['refused']}</td><td>{row['failed']}</td><td>{num(tip['median'])}</td><td>{num(tip['p90'])}</td>"
            f"<td>{num(row['time_s_per_episode'])}</td>"
            f"<td><a href=\"{e(row['results'])}\">results.jsonl</a></td></tr>")
    failures = []
    for cell, res in zip(cells, per_cell):
        rel = cell.folder.relative_to(out)
        for r in res:
            if outcome_of(r) == "grasped":
                continue
            rec = r.get("recording")
            link = (f"<a href=\"{e(str(rel / rec))}\">{e(rec)}</a>" if rec and (cell.folder / rec).is_file()
                    else "&mdash;")
            drawn = ", ".join(f"{k}={v}" for k, v in (r.get("randomize") or {}).items())
            failures.append(
                f"<tr><td>{e(_label(cell.point))}</td><td>{r.get('seed')}</td><td class=\"{e(outcome_of(r))}\">"
                f"{e(outcome_of(r))}</td><td>{e(str(r.get('failure')))}</td><td>{e(str(r.get('verdict')))}</td>"
                f"<td>{num(r.get('tip_error_mm'))}</td><td>{link}</td><td class=\"small\">{e(drawn)}</td>"
                f"<td class=\"small\">{e(str(r.get('detail') or r.get('verdict_reason') or ''))[:300]}</td></tr>")
    settings_rows = [("command", s.get("command", "")), ("cell file", s.get("config") or "bundled (assets/cell.toml)"),
                     ("episodes per cell", s["n"]), ("seeds", f"{s['seeds'][0]} .. {s['seeds'][1]} (the same in every cell)"),
                     ("backend", f"{s['backend']}" + (f" at {s['address']}" if s.get("address") else "")
                      + f", {s['jobs']} worker(s)"),
                     ("cameras (unless swept)", s["cameras"]),
                     ("randomisation besides the grid", ", ".join(f"{k} = {v}" for k, v in s["randomize"].items())
                      or "none (the cell file's values)"),
                     ("grid", "; ".join(f"{k}: {', '.join(map(str, v))}" for k, v in s["params"].items())),
                     ("this run", f"{s['episodes_this_run']} episodes in {s['wall_s_this_run']:.0f} s"),
                     ("written", datetime.datetime.now().astimezone().strftime("%Y-%m-%d %H:%M %Z"))]
    figs = "\n".join(f"<figure><img src=\"{PLOTS}/{e(name)}\" alt=\"{e(title)}\"><figcaption>{e(title)}</figcaption>"
                     f"</figure>" for name, title in plots)
    return f"""<!DOCTYPE html>
<html lang="en"><head><meta charset="utf-8"><title>tapecell sweep</title>
<style>
body {{ font-family: sans-serif; margin: 2em auto; max-width: 1100px; color: #222; }}
table {{ border-collapse: collapse; margin: 1em 0; }}
th, td {{ border: 1px solid #ccc; padding: 3px 8px; text-align: left; }}
th {{ background: #f3f3f3; }}
td.failed {{ color: #b00; font-weight: bold; }} td.refused {{ color: #a60; }}
td.small {{ font-size: 85%; color: #555; }}
figure {{ display: inline-block; margin: 0.5em; }} img {{ max-width: 100%; border: 1px solid #ddd; }}
</style></head><body>
<h1>Grasp sweep</h1>
<p>Simulated grasp episodes (<code>tape-episode/1</code>) over a grid of settings: each row of the table is one
cell of the grid, run on the same seeds. <em>grasped</em>: the tape held through the lift; <em>refused</em>: the
system declined and touched nothing (safe); <em>failed</em>: it acted and did not take the tape (the worst
outcome). Intervals are 95 % Wilson intervals of the success rate. Summary: <a href="summary.json">summary.json</a>
(<code>tape-sweep/1</code>).</p>
<h2>Settings</h2>
<table>{''.join(f"<tr><th>{e(k)}</th><td>{e(str(v))}</td></tr>" for k, v in settings_rows)}</table>
<h2>Results</h2>
<table><tr><th>cell</th><th>n</th><th>grasped</th><th>rate</th><th>95 % interval</th><th>refused</th><th>failed</th>
<th>tip error median [mm]</th><th>tip error p90 [mm]</th><th>time per episode [s]</th><th>episodes</th></tr>
{''.join(table)}</table>
<h2>Plots</h2>
{figs}
<h2>Episodes not grasped</h2>
<p>{len(failures)} episode(s). Recordings open with <code>rerun FILE</code> (written for the episodes that did not
grasp unless the sweep ran with <code>--rrd none</code>).</p>
<table><tr><th>cell</th><th>seed</th><th>outcome</th><th>reason</th><th>verdict</th><th>tip error [mm]</th>
<th>recording</th><th>drawn</th><th>detail</th></tr>
{''.join(failures) or '<tr><td colspan="9">none</td></tr>'}</table>
</body></html>
"""
