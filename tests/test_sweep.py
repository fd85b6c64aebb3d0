"""tapecell sweep: the grid, the tape-sweep/1 summary, the report and its plots, bad input;
the campaign runner's progress display and its process pool surviving a dead worker."""
from __future__ import annotations

import io
import json
import os
from pathlib import Path

import cv2
import numpy as np
import pytest

from tapecell.cli.main import main
from tapecell.sim.episodes import EpisodeJob, Progress, load_results, run_episodes, wilson_interval
from tapecell.sim.randomize import Randomize
from tapecell.sim.sweep import SweepError, grid, parse_param, run_sweep


def fake_worker(job: EpisodeJob) -> dict:
    """Outcomes that depend on the cell's settings: 3 cameras and no calibration error help."""
    rot = job.randomize.settings.get("calib_rot_deg", 0.0) if job.randomize else 0.0
    rng = np.random.default_rng([job.seed, job.cameras, int(1000 * rot)])
    u = rng.random()
    good = (0.9 if job.cameras == 3 else 0.7) - rot
    outcome = "grasped" if u < good else "refused" if u < good + 0.2 else "failed"
    doc = {"format": "tape-episode/1", "seed": job.seed, "cameras": job.cameras, "success": outcome == "grasped",
           "outcome": outcome, "verdict": "ambiguous" if outcome == "refused" else "ok",
           "failure": {"grasped": None, "refused": "estimate rejected", "failed": "slipped"}[outcome],
           "tip_error_mm": round(float(rng.lognormal(-0.5 + 3 * rot, 0.5)), 3),
           "time_s": {"capture": 0.5, "execute": 2.0}}
    if rot:
        doc["randomize"] = {"calib_rot_deg": rot}
    if job.recording is not None:
        job.recording.write_bytes(b"rrd")
        doc["recording"] = job.recording.name
        if outcome == "grasped" and job.failures_only:
            job.recording.unlink()
            del doc["recording"]
    return doc


def test_params_parse_and_make_a_grid():
    a = parse_param("cameras=2,3")
    b = parse_param("randomize.calib_rot_deg=0,0.3")
    c = parse_param("randomize.tape_width_mm=15:25,25:35")
    assert a.values == (2, 3) and b.values == (0.0, 0.3) and b.setting == "calib_rot_deg"
    assert c.values == ((15.0, 25.0), (25.0, 35.0))
    assert grid([a, b]) == [{"cameras": 2, "randomize.calib_rot_deg": 0.0}, {"cameras": 2, "randomize.calib_rot_deg": 0.3},
                            {"cameras": 3, "randomize.calib_rot_deg": 0.0}, {"cameras": 3, "randomize.calib_rot_deg": 0.3}]


@pytest.mark.parametrize("text, words", [
    ("light=1,2", "unknown parameter"),
    ("randomize.colour=1", "unknown randomisation setting"),
    ("cameras=2,4", "cameras must be 2 or 3"),
    ("randomize.calib_rot_deg=0,abc", "not a number"),
    ("randomize.calib_rot_deg=0,99", "outside"),
    ("randomize.tape_width_mm=30:20", "reversed"),
    ("cameras=", "expected NAME=V1,V2"),
    ("cameras=2,,3", "expected NAME=V1,V2"),
    ("cameras=2,2", "repeated"),
])
def test_bad_params_are_named(text, words):
    with pytest.raises(SweepError, match=words):
        parse_param(text)


def test_sweep_writes_summary_report_and_plots(tmp_path):
    out = tmp_path / "sw"
    params = [parse_param("cameras=2,3"), parse_param("randomize.calib_rot_deg=0,0.3")]
    summary = run_sweep(params, 30, 100, out, worker=fake_worker, base=Randomize(), rrd="failures",
                        progress_stream=io.StringIO())
    doc = json.loads((out / "summary.json").read_text())
    assert doc == summary and doc["format"] == "tape-sweep/1" and len(doc["rows"]) == 4
    for row in doc["rows"]:
        assert set(row) >= {"params", "n", "success", "rate", "ci95", "refused", "failed", "tip_error_mm",
                            "time_s_per_episode"}
        results = load_results(out / row["results"])
        assert [r["seed"] for r in results] == list(range(100, 130)) and row["n"] == 30
        grasped = sum(r["outcome"] == "grasped" for r in results)
        assert row["success"] == grasped and row["rate"] == pytest.approx(grasped / 30, abs=1e-4)
        assert row["ci95"] == pytest.approx(list(wilson_interval(grasped, 30)), abs=1e-4)
        assert row["refused"] + row["failed"] + grasped == 30
        tips = [r["tip_error_mm"] for r in results]
        assert row["tip_error_mm"]["median"] == pytest.approx(np.median(tips), abs=1e-3)
        assert row["tip_error_mm"]["p90"] == pytest.approx(np.percentile(tips, 90), abs=1e-3)
        assert row["time_s_per_episode"] == pytest.approx(2.5)
    by = {(r["params"]["cameras"], r["params"]["randomize.calib_rot_deg"]): r for r in doc["rows"]}
    assert by[(3, 0.0)]["rate"] > by[(2, 0.3)]["rate"]          # the fake's settings show through
    # plots: real PNG images with something drawn on them
    for name in ("rate_cameras.png", "rate_calib_rot_deg.png", "tip_error.png", "reasons.png"):
        img = cv2.imread(str(out / "plots" / name))
        assert img is not None and img.shape[0] > 150 and img.shape[1] >= 700, name
        assert (img < 200).mean() > 0.01, f"{name} is blank"
    page = (out / "report.html").read_text()
    for name in ("plots/rate_cameras.png", "plots/tip_error.png", "plots/reasons.png", "summary.json"):
        assert f'"{name}"' in page
    # every episode not grasped is listed with a link to its recording, and only those are kept
    kept = sorted(out.glob("cells/*/episode-*.rrd"))
    assert len(kept) == sum(r["n"] - r["success"] for r in doc["rows"]) > 0
    for rec in kept:
        assert f'href="{rec.relative_to(out)}"' in page
    assert not list(out.glob("**/.*"))      # no temporary files left
    # a rerun runs nothing and gives the same rows
    calls = []

    def counting(job):
        calls.append(job)
        return fake_worker(job)

    again = run_sweep(params, 30, 100, out, worker=counting, base=Randomize(), rrd="failures",
                      progress_stream=io.StringIO())
    assert calls == [] and again["rows"] == summary["rows"]


def test_sweep_cli_runs_real_episodes(tmp_path, capsys):
    """The issue's command at --n 1: four grid cells of real episodes, a valid summary and a
    report with its plots."""
    out = tmp_path / "sweep"
    code = main(["sweep", "--param", "cameras=2,3", "--param", "randomize.calib_rot_deg=0,0.3", "--n", "1",
                 "--seed", "1", "--jobs", "2", "--rrd", "none", "--out", str(out)])
    text, err = capsys.readouterr()
    assert code == 0, err
    doc = json.loads((out / "summary.json").read_text())
    assert doc["format"] == "tape-sweep/1" and len(doc["rows"]) == 4
    assert [r["params"] for r in doc["rows"]] == [
        {"cameras": c, "randomize.calib_rot_deg": v} for c in (2, 3) for v in (0.0, 0.3)]
    for row in doc["rows"]:
        assert row["n"] == 1 and row["success"] + row["refused"] + row["failed"] == 1
        results = load_results(out / row["results"])
        assert results[0]["cameras"] == row["params"]["cameras"]
        rot = row["params"]["randomize.calib_rot_deg"]
        assert results[0]["randomize"]["calib_rot_deg"] == rot
    assert (out / "report.html").is_file() and len(list((out / "plots").glob("*.png"))) == 4
    assert "cameras=3 calib_rot_deg=0.3" in text and "report.html" in text


@pytest.mark.parametrize("argv, words", [
    (["--param", "bogus=1"], "unknown parameter"),
    (["--param", "randomize.calib_rot_deg=x"], "not a number"),
    (["--param", "cameras=2", "--param", "cameras=3"], "given twice"),
    (["--param", "cameras=2", "--config", "/nonexistent/cell.toml"], "cell file not found"),
    (["--param", "cameras=2", "--address", "127.0.0.1:6379"], "--address needs --backend ray"),
    (["--param", "cameras=2", "--randomize", "calib_rot_deg"], "expected NAME=VALUE"),
])
def test_sweep_bad_input_is_one_line(tmp_path, capsys, argv, words):
    code = main(["sweep", "--n", "1", "--out", str(tmp_path / "o")] + argv)
    out, err = capsys.readouterr()
    assert code == 2 and out == ""
    assert err.count("\n") == 1 and words in err and "Traceback" not in err
    assert not (tmp_path / "o").exists()


def test_help_explains_every_option(capsys):
    for cmd, options in (("sweep", ("--param", "--n", "--rrd")), ("episodes", ("--n", "--rrd"))):
        with pytest.raises(SystemExit):
            main([cmd, "--help"])
        text = capsys.readouterr().out
        for option in options + ("--backend", "--address", "--randomize", "--jobs", "--out"):
            assert option in text, (cmd, option)


def test_progress_is_a_bar_on_a_terminal_and_lines_in_a_log():
    class Tty(io.StringIO):
        def isatty(self):
            return True

    log, tty = io.StringIO(), Tty()
    for stream in (log, tty):
        p = Progress(3, stream)
        for seed, outcome in ((0, "grasped"), (1, "refused"), (2, "failed")):
            p.update({"seed": seed, "outcome": outcome, "failure": None if outcome == "grasped" else "x"})
    lines = log.getvalue().splitlines()
    assert len(lines) == 3 and lines[-1].startswith("3/3 episodes") and "ep/s" in lines[-1] and "left" in lines[-1]
    assert "grasped 1 refused 1 failed 1" in lines[-1] and "seed 2 failed (x)" in lines[-1]
    shown = tty.getvalue()
    assert shown.count("\r") == 3 and shown.endswith("\n") and "[" in shown and "left 0:00" in shown


def _dies_on_seed_3(job: EpisodeJob) -> dict:
    """Kills its own worker process on seed 3 (every time) and on seed 5 (the first time)."""
    marker = Path(os.environ["TAPECELL_TEST_MARKER"])
    if job.seed == 3 or (job.seed == 5 and not marker.exists()):
        if job.seed == 5:
            marker.write_text("died once")
        os._exit(1)
    return {"format": "tape-episode/1", "seed": job.seed, "cameras": job.cameras, "success": True,
            "outcome": "grasped"}


def test_process_pool_survives_a_dead_worker(tmp_path, monkeypatch):
    """A worker that dies loses only its episode: run once more, then reported; the
    others (also those in flight with it) complete."""
    monkeypatch.setenv("TAPECELL_TEST_MARKER", str(tmp_path / "marker"))
    results = run_episodes(range(8), 2, tmp_path / "c", jobs=2, worker=_dies_on_seed_3,
                           progress_stream=io.StringIO())
    assert [r["seed"] for r in results] == list(range(8))
    bad = [r for r in results if not r["success"]]
    assert [(r["seed"], r["failure"], r["outcome"]) for r in bad] == [(3, "worker died", "failed")]
    assert (tmp_path / "marker").exists()          # seed 5 died once and was run again


def test_rerun_runs_again_an_episode_whose_worker_died(tmp_path):
    from tapecell.sim.episodes import append_result, worker_died

    out = tmp_path / "c"
    out.mkdir()
    append_result(out / "results.jsonl", worker_died(EpisodeJob(2, 2, None, None), "machine lost"))
    calls = []

    def worker(job):
        calls.append(job.seed)
        return {"format": "tape-episode/1", "seed": job.seed, "cameras": job.cameras, "success": True,
                "outcome": "grasped"}

    results = run_episodes(range(4), 2, out, worker=worker, progress_stream=io.StringIO())
    assert calls == [0, 1, 2, 3]
    assert [r["outcome"] for r in results] == ["grasped"] * 4      # the new line replaces the old
    assert run_episodes(range(4), 2, out, worker=worker, progress_stream=io.StringIO()) == results
    assert calls == [0, 1, 2, 3]


def test_ray_backend_without_ray_says_how_to_install(tmp_path, capsys, monkeypatch):
    import sys

    monkeypatch.setitem(sys.modules, "ray", None)       # import ray -> ImportError
    code = main(["episodes", "--n", "1", "--backend", "ray", "--out", str(tmp_path / "o")])
    out, err = capsys.readouterr()
    assert code == 2 and err.count("\n") == 1 and 'pip install "tapecell[ray]"' in err
    assert not (tmp_path / "o").exists()
