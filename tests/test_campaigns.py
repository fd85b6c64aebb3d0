"""Campaigns at scale: domain randomisation, sweeps with their report, the Ray backend."""
from __future__ import annotations

import json
import os
import socket
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from tapecell.estimator.synthetic import SyntheticOptions, make_capture
from tapecell.sim.randomize import Randomize, RandomizeError, apply_to_capture, apply_to_config
from tapecell.sim.sweep import SweepError, grid, parse_params

pytestmark = pytest.mark.filterwarnings("ignore::DeprecationWarning")


def test_randomize_settings_are_checked():
    r = Randomize.from_table({"calib_rot_deg": [0.0, 0.5], "cameras": [2, 3], "ambient": 0.3})
    assert r.settings == {"calib_rot_deg": (0.0, 0.5), "cameras": (2, 3), "ambient": 0.3}
    r = r.with_overrides(["tape_width_mm=20:30", "ambient=0.4"])
    assert r.settings["tape_width_mm"] == (20.0, 30.0) and r.settings["ambient"] == 0.4
    for bad, match in [({"calib_rot": 1.0}, "unknown setting 'calib_rot'"), ({"ambient": [0.5, 0.2]}, "reversed"),
                       ({"calib_rot_deg": 90.0}, "outside"), ({"cameras": 4}, "one of"),
                       ({"tape_model": "shell"}, "no arm"), ({"ambient": "bright"}, "finite number")]:
        with pytest.raises(RandomizeError, match=match):
            Randomize.from_table(bad)
    with pytest.raises(RandomizeError, match="NAME=VALUE"):
        Randomize().with_overrides(["ambient"])
    with pytest.raises(RandomizeError, match="not a number"):
        Randomize().with_overrides(["ambient=a:b"])


def test_draws_are_reproducible_from_the_seed_and_independent():
    r = Randomize.from_table({"calib_rot_deg": [0.0, 0.5], "tape_width_mm": [20.0, 30.0], "cameras": [2, 3]})
    a, b = r.draw(7), r.draw(7)
    assert a == b and set(a) == {"calib_rot_deg", "tape_width_mm", "cameras"}
    assert 0.0 <= a["calib_rot_deg"] <= 0.5 and 20.0 <= a["tape_width_mm"] <= 30.0
    assert len({json.dumps(r.draw(s)) for s in range(20)}) == 20
    # Adding a setting does not change what the others draw.
    more = Randomize(dict(r.settings, ambient=(0.2, 0.5))).draw(7)
    assert {k: more[k] for k in a} == a
    assert Randomize().draw(7) == {}
    cams = [r.draw(s)["cameras"] for s in range(40)]
    assert set(cams) == {2, 3}


def test_calibration_error_and_mask_noise_reach_the_estimator_only():
    capture = make_capture(5, SyntheticOptions(cameras=2))
    drawn = {"calib_rot_deg": 0.3, "calib_trans_mm": 2.0, "mask_noise": 1.0}
    out = apply_to_capture(capture, drawn, seed=5)
    for v0, v1 in zip(capture.views, out.views):
        dR = v1.camera.R @ v0.camera.R.T
        angle = np.degrees(np.arccos(np.clip((np.trace(dR) - 1) / 2, -1, 1)))
        assert angle == pytest.approx(0.3, abs=1e-6)
        assert np.linalg.norm(v1.camera.center - v0.camera.center) == pytest.approx(0.002, abs=1e-9)
        changed = np.count_nonzero(v1.mask != v0.mask)
        assert 0 < changed < 0.2 * np.count_nonzero(v0.mask)
    assert out.truth is capture.truth and out.scene == capture.scene
    assert apply_to_capture(capture, {}, seed=5) is capture


def test_tape_settings_change_the_cell_config():
    from tapecell.cell.config import load_cell_config

    cfg = load_cell_config()
    out = apply_to_config(cfg, {"tape_width_mm": 24.0, "tape_stiffness_scale": 2.0, "tape_rgb_jitter": 0.1}, 3)
    assert out.tape.width == pytest.approx(0.024)
    assert out.tape.flat_bend_stiffness == pytest.approx(2 * cfg.tape.flat_bend_stiffness)
    assert np.max(np.abs(np.subtract(out.tape.rgba, cfg.tape.rgba))) <= 0.1 + 1e-12
    assert apply_to_config(cfg, {}, 3) is cfg


def test_randomize_table_in_a_cell_file(tmp_path):
    from tapecell.cell.config import load_cell_config, default_cell_path

    text = default_cell_path().read_text() + "\n[randomize]\ncalib_rot_deg = [0.0, 0.3]\ncameras = [2, 3]\n"
    path = tmp_path / "cell.toml"
    path.write_text(text)
    cfg = load_cell_config(path)
    assert Randomize.from_table(cfg.randomize).settings == {"calib_rot_deg": (0.0, 0.3), "cameras": (2, 3)}


def test_sweep_params_are_checked():
    params = parse_params(["cameras=2,3", "randomize.calib_rot_deg=0,0.3"])
    assert params == [("cameras", [2, 3]), ("randomize.calib_rot_deg", [0.0, 0.3])]
    assert len(grid(params)) == 4 and grid([]) == [{}]
    for bad, match in [(["cameras=4"], "2 or 3"), (["light=1"], "sweepable"), (["cameras"], "NAME=V1"),
                       (["randomize.calib_rot_deg=0,9"], "outside"), (["cameras=2", "cameras=3"], "twice"),
                       (["randomize.ambient=0.2,0.2"], "repeated"), (["randomize.nope=1"], "unknown setting")]:
        with pytest.raises(SweepError, match=match):
            parse_params(bad)


def test_sweep_writes_a_summary_and_a_report(tmp_path, capsys):
    """The issue's sweep, one episode a cell: four rows, a valid tape-sweep/1 summary, a report
    whose plots are PNG files it links."""
    from tapecell.cli.main import main

    out = tmp_path / "sweep"
    code = main(["sweep", "--param", "cameras=2,3", "--param", "randomize.calib_rot_deg=0,0.3", "--n", "1",
                 "--seed", "11", "--jobs", "2", "--out", str(out)])
    assert code == 0
    summary = json.loads((out / "summary.json").read_text())
    assert summary["format"] == "tape-sweep/1" and len(summary["rows"]) == 4
    seen = set()
    for row in summary["rows"]:
        seen.add((row["params"]["cameras"], row["params"]["randomize.calib_rot_deg"]))
        assert row["n"] == 1 and row["success"] + row["refused"] + row["failed"] == 1
        assert 0 <= row["ci95"][0] <= row["rate"] <= row["ci95"][1] <= 1
        assert set(row["tip_error_mm"]) == {"median", "p90"} and row["time_s_per_episode"] > 0
        result = json.loads((out / row["dir"] / "results.jsonl").read_text().splitlines()[0])
        assert result["cameras"] == row["params"]["cameras"]
        assert result["randomize"]["calib_rot_deg"] == row["params"]["randomize.calib_rot_deg"]
    assert seen == {(2, 0.0), (2, 0.3), (3, 0.0), (3, 0.3)}
    page = (out / "report.html").read_text()
    pngs = sorted(p.name for p in out.glob("plot-*.png"))
    assert len(pngs) >= 4 and all(f'src="{p}"' in page for p in pngs)
    assert all((out / p).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" for p in pngs)


def test_sweep_bad_param_is_one_line(capsys):
    from tapecell.cli.main import main

    assert main(["sweep", "--param", "randomize.calib_rot=1", "--n", "1", "--out", "/tmp/x"]) != 0
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "unknown setting 'calib_rot'" in err[0]


# --------------------------------------------------------------------------------- Ray

def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.fixture(scope="module")
def ray_cluster(tmp_path_factory):
    """A two-worker Ray cluster started with ``ray start --head``, bound to loopback."""
    import secrets

    port = _free_port()
    tmp = tmp_path_factory.mktemp("ray")
    # Ray >= 2.59 authenticates clients of a cluster with a token: the same one on both sides.
    auth = {"RAY_AUTH_MODE": "token", "RAY_AUTH_TOKEN": secrets.token_hex(16)}
    saved = {k: os.environ.get(k) for k in ("RAY_TMPDIR", *auth)}
    # Before Ray is imported: serve on the loopback address only (see sim/ray_backend.py),
    # and the token this process will present.
    os.environ.setdefault("RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER", "0")
    os.environ.update(RAY_TMPDIR=str(tmp), **auth)
    pytest.importorskip("ray")
    import ray

    env = dict(os.environ, RAY_TMPDIR=str(tmp), RAY_USAGE_STATS_ENABLED="0", RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER="0",
               **auth)
    ray_bin = Path(sys.executable).parent / "ray"
    start = subprocess.run([str(ray_bin), "start", "--head", "--node-ip-address", "127.0.0.1", "--port", str(port),
                            "--num-cpus", "2", "--include-dashboard=false", "--disable-usage-stats"],
                           env=env, capture_output=True, text=True, timeout=120)
    if start.returncode != 0:
        pytest.skip(f"ray start failed: {start.stderr.strip().splitlines()[-1:]}")
    try:
        yield f"127.0.0.1:{port}"
    finally:
        if ray.is_initialized():
            ray.shutdown()
        subprocess.run([str(ray_bin), "stop", "--force"], env=env, capture_output=True, timeout=120)
        for k, v in saved.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v


def _dies_once(job):
    """A worker whose process dies the first time it runs a seed (a crashed machine)."""
    marker = job.recording.with_suffix(".tried")
    if not marker.exists():
        marker.write_text("x")
        os._exit(1)
    return {"format": "tape-episode/1", "seed": job.seed, "cameras": job.cameras, "success": True,
            "outcome": "grasped", "failure": None, "time_s": {}}


def _always_dies(job):
    os._exit(1)


def test_ray_same_results_as_the_process_pool_and_dead_workers(ray_cluster, tmp_path):
    """Two seeds through the process pool and through the ``ray start`` cluster give the same
    episodes; a worker that dies is retried once, one that dies again is reported."""
    from tapecell.sim.episodes import load_results, run_episodes
    from tapecell.sim.ray_backend import run_on_ray, start

    ray = start(2, ray_cluster)
    assert ray.is_initialized()
    # Loopback only: every Ray node serves on 127.0.0.1.
    assert {n["NodeManagerAddress"] for n in ray.nodes()} == {"127.0.0.1"}
    pool = run_episodes([3, 4], 2, tmp_path / "pool", jobs=2)
    cluster = run_episodes([3, 4], 2, tmp_path / "ray", jobs=2, backend="ray", address=ray_cluster)
    for a, b in zip(pool, cluster):
        a, b = dict(a), dict(b)
        a.pop("time_s"), b.pop("time_s")
        assert a == b
    assert len(load_results(tmp_path / "ray" / "results.jsonl")) == 2

    from tapecell.sim.episodes import EpisodeJob
    # The fake workers live in this test module, which Ray's workers cannot import: by value.
    ray.cloudpickle.register_pickle_by_value(sys.modules[__name__])
    jobs = [EpisodeJob(s, 2, tmp_path / f"ep{s}.rrd", None) for s in (1, 2)]
    docs = sorted(run_on_ray(jobs, 2, ray_cluster, _dies_once), key=lambda d: d["seed"])
    assert [d["outcome"] for d in docs] == ["grasped", "grasped"], [d.get("detail") for d in docs]
    t0 = time.perf_counter()
    docs = list(run_on_ray(jobs[:1], 2, ray_cluster, _always_dies))
    assert docs[0]["outcome"] == "failed" and docs[0]["failure"] == "worker died", docs
    assert time.perf_counter() - t0 < 120


def test_ray_backend_errors_are_one_line(tmp_path):
    from tapecell.estimator.errors import TapecellError
    from tapecell.sim.episodes import run_episodes

    with pytest.raises(TapecellError, match="needs --backend ray"):
        run_episodes([1], 2, tmp_path, address="127.0.0.1:1")
    with pytest.raises(TapecellError, match="--backend must be"):
        run_episodes([1], 2, tmp_path, backend="dask")
