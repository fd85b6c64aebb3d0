"""Domain randomisation of sim episodes: settings from the cell file and the command line,
values drawn reproducibly from the episode's seed and recorded in its result, applied to
the scene (light, tape) and to what the estimator gets (calibration error, mask noise)."""
from __future__ import annotations

import json
import re

import numpy as np
import pytest

from tapecell.cell.config import default_cell_path, load_cell_config
from tapecell.cli.main import main
from tapecell.estimator.synthetic import SyntheticOptions, make_capture
from tapecell.sim.randomize import Randomize, RandomizeError, apply_to_capture, apply_to_config


def test_draws_are_reproducible_per_seed_and_independent_per_setting():
    r = Randomize.from_table({"light_intensity": [0.2, 1.0], "tape_width_mm": [15.0, 25.0], "ambient": 0.5,
                              "cameras": [2, 3]})
    a, b = r.draw(7), r.draw(7)
    assert a == b and set(a) == {"light_intensity", "tape_width_mm", "ambient", "cameras"}
    assert 0.2 <= a["light_intensity"] <= 1.0 and 15.0 <= a["tape_width_mm"] <= 25.0 and a["ambient"] == 0.5
    draws = [r.draw(s) for s in range(200)]
    widths = [d["tape_width_mm"] for d in draws]
    assert len(set(widths)) == 200 and 15.0 <= min(widths) < 16.0 and 24.0 < max(widths) <= 25.0
    assert {d["cameras"] for d in draws} == {2, 3}
    # adding a setting does not change another's values
    only = Randomize.from_table({"tape_width_mm": [15.0, 25.0]})
    assert [only.draw(s)["tape_width_mm"] for s in range(200)] == widths
    assert Randomize().draw(3) == {}


@pytest.mark.parametrize("table, words", [
    ({"colour": 1.0}, "unknown setting"),
    ({"tape_width_mm": [25.0, 15.0]}, "reversed"),
    ({"calib_rot_deg": 9.0}, "outside"),
    ({"light_intensity": True}, "finite number"),
    ({"tape_width_mm": [1.0, 2.0, 3.0]}, "number or a [lo, hi] range"),
    ({"cameras": [2, 4]}, "must be one of"),
    ({"tape_model": "ribbon"}, "must be one of"),
])
def test_bad_settings_are_named(table, words):
    with pytest.raises(RandomizeError, match=re.escape(words)):
        Randomize.from_table(table)


def test_command_line_overrides_the_table():
    r = Randomize.from_table({"ambient": 0.5}).with_overrides(["ambient=0.2:0.4", "cameras=2,3", "mask_noise=1"])
    assert r.settings == {"ambient": (0.2, 0.4), "cameras": (2, 3), "mask_noise": 1.0}
    with pytest.raises(RandomizeError, match="expected NAME=VALUE"):
        r.with_overrides(["ambient"])


def test_cell_file_table_is_read_and_checked(tmp_path, capsys):
    good = tmp_path / "good.toml"
    good.write_text(default_cell_path().read_text() + "\n[randomize]\ntape_width_mm = [20.0, 30.0]\n")
    assert load_cell_config(good).randomize == {"tape_width_mm": [20.0, 30.0]}
    bad = tmp_path / "bad.toml"
    bad.write_text(default_cell_path().read_text() + "\n[randomize]\ntape_width_mm = [30.0, 20.0]\n")
    code = main(["episodes", "--n", "1", "--config", str(bad), "--out", str(tmp_path / "o")])
    out, err = capsys.readouterr()
    assert code == 2 and err.count("\n") == 1 and "reversed" in err and str(bad) in err
    assert not (tmp_path / "o").exists()


def test_tape_settings_change_the_config():
    cfg = load_cell_config()
    changed = apply_to_config(cfg, {"tape_width_mm": 20.0, "tape_length_mm": 120.0, "tape_stiffness_scale": 2.0,
                                    "tape_rgb_jitter": 0.2}, seed=3)
    assert changed.tape.width == pytest.approx(0.020) and changed.tape.length == pytest.approx(0.120)
    assert changed.tape.flat_bend_stiffness == pytest.approx(2 * cfg.tape.flat_bend_stiffness)
    assert np.abs(np.subtract(changed.tape.rgba[:3], cfg.tape.rgba[:3])).max() <= 0.2 + 1e-12
    assert changed.tape.rgba != cfg.tape.rgba
    assert apply_to_config(cfg, {}, seed=3) is cfg


def test_calibration_error_moves_the_estimators_cameras_only():
    cap = make_capture(5, SyntheticOptions(cameras=2))
    out = apply_to_capture(cap, {"calib_rot_deg": 0.3, "calib_trans_mm": 2.0}, seed=5)
    assert out.truth is cap.truth and out.scene == cap.scene
    for v0, v1 in zip(cap.views, out.views):
        dR = v1.camera.R @ v0.camera.R.T
        angle = np.degrees(np.arccos(np.clip((np.trace(dR) - 1) / 2, -1, 1)))
        assert angle == pytest.approx(0.3, abs=1e-6)
        assert np.linalg.norm(v1.camera.center - v0.camera.center) == pytest.approx(0.002, abs=1e-9)
        assert np.array_equal(v1.mask, v0.mask)
    again = apply_to_capture(cap, {"calib_rot_deg": 0.3, "calib_trans_mm": 2.0}, seed=5)
    assert all(np.allclose(a.camera.R, b.camera.R) for a, b in zip(out.views, again.views))
    noisy = apply_to_capture(cap, {"mask_noise": 1.0}, seed=5)
    assert any(not np.array_equal(a.mask, b.mask) for a, b in zip(cap.views, noisy.views))
    assert apply_to_capture(cap, {}, seed=5) is cap


def test_episode_records_what_it_drew(capsys):
    code = main(["episode", "--seed", "4", "--randomize", "light_intensity=0.4:0.8", "--randomize",
                 "calib_rot_deg=0.1"])
    out, err = capsys.readouterr()
    doc = json.loads(out)
    expected = Randomize.from_table({"light_intensity": [0.4, 0.8], "calib_rot_deg": 0.1}).draw(4)
    assert doc["randomize"] == expected and doc["seed"] == 4
    assert code == (0 if doc["success"] else 1)


def test_an_episode_that_ends_in_an_error_records_what_it_drew(monkeypatch):
    """A campaign's episode that ends in an error (here: no tape shape the cameras see
    whole, as for a tape drawn too long) still says which values its seed drew, so the
    setting that broke it can be found and the episode re-run alone."""
    from tapecell.estimator.errors import TapecellError
    from tapecell.sim import episode

    def no_shape(seed, *a, **k):
        raise TapecellError(f"no 'twist' tape shape for seed {seed} fits the cameras' view")
    monkeypatch.setattr(episode, "run_episode", no_shape)
    r = Randomize.from_table({"tape_length_mm": [200, 250], "cameras": [2, 3]})
    assert r.draw(7)["cameras"] == 2
    doc = episode.run_episode_safely(7, 3, None, None, r)   # the drawn camera count stands
    assert doc["outcome"] == "failed" and doc["failure"] == "error" and "seed 7" in doc["detail"]
    assert doc["randomize"] == r.draw(7) and doc["cameras"] == r.draw(7)["cameras"]
    plain = episode.run_episode_safely(7, 3, None, None, Randomize.from_table({}))
    assert "randomize" not in plain and plain["cameras"] == 3
