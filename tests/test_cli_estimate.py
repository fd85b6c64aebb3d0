"""`tapecell estimate` through the command: outputs, and one clear line for every bad input."""
from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

from tapecell.cli.main import main
from tapecell.estimator.capture import load_capture, save_capture
from tapecell.estimator.synthetic import SyntheticOptions, make_capture


@pytest.fixture(scope="module")
def good_capture(tmp_path_factory) -> Path:
    path = tmp_path_factory.mktemp("caps") / "good"
    save_capture(make_capture(3, SyntheticOptions(kind="chain", cameras=2)), path)
    return path


@pytest.fixture
def capture_copy(good_capture, tmp_path) -> Path:
    import shutil
    dst = tmp_path / "cap"
    shutil.copytree(good_capture, dst)
    return dst


def _edit_json(path: Path, fn) -> None:
    doc = json.loads((path / "capture.json").read_text())
    fn(doc)
    (path / "capture.json").write_text(json.dumps(doc))


def _run(argv, capsys):
    code = main([str(a) for a in argv])
    out, err = capsys.readouterr()
    return code, out, err


def test_single_capture_prints_estimate_json(good_capture, capsys):
    code, out, err = _run(["estimate", good_capture], capsys)
    assert code == 0, err
    doc = json.loads(out)
    assert doc["format"] == "tape-estimate/1"
    assert len(doc["nodes"]) == 6 and len(doc["angles"]) == 5
    assert len(doc["view_costs"]) == 2 and doc["time_s"] > 0
    truth = load_capture(good_capture).truth
    assert np.linalg.norm(np.array(doc["tip"]["position"]) - truth.tip_position) < 0.002
    R = np.array(doc["tip"]["rotation"])
    assert np.allclose(R @ R.T, np.eye(3), atol=1e-9)
    assert np.allclose(doc["nodes"][-1], doc["tip"]["position"])


def _corrupt_missing_json(p): (p / "capture.json").unlink()
def _corrupt_missing_mask(p): (p / "cam1.png").unlink()
def _corrupt_format(p): _edit_json(p, lambda d: d.update(format="tape-capture/9"))
def _corrupt_size(p): cv2.imwrite(str(p / "cam0.png"), np.zeros((100, 120), np.uint8))
def _corrupt_empty(p): cv2.imwrite(str(p / "cam1.png"), np.zeros((480, 640), np.uint8))
def _corrupt_rotation(p): _edit_json(p, lambda d: d["cameras"][0].update(R=[[1, 0, 0], [0, 2, 0], [0, 0, 1]]))
def _corrupt_nan(p): _edit_json(p, lambda d: d["cameras"][1].update(t=[0.0, float("nan"), 0.6]))
def _corrupt_inf(p): _edit_json(p, lambda d: d["tape"]["base"].update(position=[0.0, float("inf"), 0.0]))
def _corrupt_no_cameras(p): _edit_json(p, lambda d: d.update(cameras=[]))


def _corrupt_ignore(p):
    cv2.imwrite(str(p / "cam0_ignore.png"), np.zeros((10, 10), np.uint8))
    _edit_json(p, lambda d: d["cameras"][0].update(ignore="cam0_ignore.png"))


def _corrupt_base_rotation(p):
    _edit_json(p, lambda d: d["tape"]["base"].update(rotation=[[1, 0, 0], [0, 1, 0], [0, 0, -1]]))


CASES = {
    "missing capture.json": (_corrupt_missing_json, "missing capture.json"),
    "missing mask": (_corrupt_missing_mask, "cam1.png: mask file not found"),
    "unknown format": (_corrupt_format, "unknown format 'tape-capture/9'"),
    "mask size": (_corrupt_size, "mask is 120x100 px but camera cam0 is 640x480"),
    "empty silhouette": (_corrupt_empty, "camera cam1 sees no tape"),
    "R not a rotation": (_corrupt_rotation, "camera cam0 R is not a rotation matrix"),
    "base rotation reflection": (_corrupt_base_rotation, "tape base rotation is not a rotation matrix"),
    "NaN": (_corrupt_nan, "camera cam1 t holds NaN or infinite numbers"),
    "infinite": (_corrupt_inf, "tape base position holds NaN or infinite numbers"),
    "ignore size": (_corrupt_ignore, "ignore mask is 10x10 px but camera cam0 is 640x480"),
    "no cameras": (_corrupt_no_cameras, "needs at least one camera"),
}


@pytest.mark.parametrize("case", list(CASES))
def test_bad_capture_gives_one_line_and_exit_2(case, capture_copy, capsys):
    corrupt, expected = CASES[case]
    corrupt(capture_copy)
    code, out, err = _run(["estimate", capture_copy], capsys)
    assert code == 2
    assert out == ""
    lines = err.strip().splitlines()
    assert len(lines) == 1, err
    assert lines[0].startswith("tapecell: error: ")
    assert expected in lines[0]
    assert str(capture_copy) in lines[0]
    assert "Traceback" not in err


def test_masks_are_thresholded_at_128(capture_copy):
    ref = load_capture(capture_copy).views[0].mask
    grey = np.where(ref, 200, 100).astype(np.uint8)  # neither 0 nor 255
    cv2.imwrite(str(capture_copy / "cam0.png"), grey)
    assert np.array_equal(load_capture(capture_copy).views[0].mask, ref)


def test_batch_with_out_writes_good_and_reports_bad(good_capture, tmp_path, capsys):
    bad = tmp_path / "bad"
    bad.mkdir()
    out_dir = tmp_path / "est"
    code, out, err = _run(["estimate", good_capture, bad, "--out", out_dir], capsys)
    assert code == 2
    doc = json.loads((out_dir / "good.json").read_text())
    assert doc["format"] == "tape-estimate/1"
    assert not (out_dir / "bad.json").exists()
    assert [p.name for p in out_dir.iterdir()] == ["good.json"]  # nothing half-written
    assert "bad" in err and "missing capture.json" in err
    good_line = next(line for line in err.splitlines() if line.startswith("good"))
    tip_mm = float(good_line.split()[4])
    assert tip_mm < 2.0
    assert "1 of 2 captures failed" in err


def test_bad_segment_option_is_one_line(good_capture, capsys):
    code, out, err = _run(["estimate", good_capture, "--segment", "hue_min"], capsys)
    assert code == 2 and err.count("\n") == 1 and "KEY=VALUE" in err


def test_colour_image_capture_is_segmented(tmp_path, capsys):
    """A capture holding colour images (no masks) goes through the OpenCV segmentation."""
    cap = make_capture(5, SyntheticOptions(kind="chain", cameras=2))
    path = save_capture(cap, tmp_path / "rgb")
    doc = json.loads((path / "capture.json").read_text())
    for cam in doc["cameras"]:
        mask = cv2.imread(str(path / cam["mask"]), cv2.IMREAD_GRAYSCALE) > 0
        img = np.full(mask.shape + (3,), (90, 90, 90), np.uint8)  # BGR grey background
        img[mask] = (200, 80, 20)  # BGR blue tape
        cv2.imwrite(str(path / f"{cam['name']}_rgb.png"), img)
        (path / cam.pop("mask")).unlink()
        cam["image"] = f"{cam['name']}_rgb.png"
    (path / "capture.json").write_text(json.dumps(doc))
    loaded = load_capture(path)
    for v, ref in zip(loaded.views, cap.views):
        iou = (v.mask & ref.mask).sum() / (v.mask | ref.mask).sum()
        assert iou > 0.98
    code, out, err = _run(["estimate", path], capsys)
    assert code == 0, err


def test_console_script_help():
    r = subprocess.run([sys.executable, "-m", "tapecell.cli.main", "estimate", "--help"], capture_output=True, text=True)
    assert r.returncode == 0 and "CAPTURE_DIR" in r.stdout
