"""No input crashes tapecell: broken masks and camera files through the command (each is
refused with one line, or fitted with a verdict that is not "ok"), and garbage handed to
the estimator directly. Everything runs in subprocesses, so a segmentation fault in a
compiled kernel is caught as a negative return code instead of killing the test run.

Fresh random masks from seeds 20000+ (never tuned on)."""
from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

from tapecell.estimator.capture import save_capture
from tapecell.estimator.synthetic import SyntheticOptions, make_capture

W, H = 640, 480


def _mask(path: Path) -> np.ndarray:
    return cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)


def _set_mask(cap: Path, cam: int, mask: np.ndarray) -> None:
    cv2.imwrite(str(cap / f"cam{cam}.png"), mask.astype(np.uint8))


def _edit(cap: Path, fn) -> None:
    doc = json.loads((cap / "capture.json").read_text())
    fn(doc)
    (cap / "capture.json").write_text(json.dumps(doc))   # json writes NaN and Infinity as such


def _rng(i: int) -> np.random.Generator:
    return np.random.default_rng(20000 + i)


# Each case breaks a copy of a good capture. "refuse": must be refused with one line naming
# a file of the capture; "fit": may be fitted, but then its verdict must not be "ok";
# "either": refused or not ok.
def random_noise(c):
    _set_mask(c, 0, np.where(_rng(0).random((H, W)) < 0.3, 255, 0))


def random_blobs(c):
    m = np.zeros((H, W), np.uint8)
    rng = _rng(1)
    for _ in range(12):
        cv2.circle(m, (int(rng.integers(W)), int(rng.integers(H))), int(rng.integers(3, 40)), 255, -1)
    _set_mask(c, 1, m)


def empty(c):
    _set_mask(c, 0, np.zeros((H, W)))


def full(c):
    _set_mask(c, 1, np.full((H, W), 255))


def inverted(c):
    _set_mask(c, 0, 255 - _mask(c / "cam0.png"))


def one_pixel(c):
    m = _mask(c / "cam0.png")
    ys, xs = np.nonzero(m)
    one = np.zeros_like(m)
    one[ys[len(ys) // 2], xs[len(xs) // 2]] = 255
    _set_mask(c, 0, one)


def one_pixel_both(c):
    for cam in (0, 1):
        m = _mask(c / f"cam{cam}.png")
        ys, xs = np.nonzero(m)
        one = np.zeros_like(m)
        one[ys[0], xs[0]] = 255
        _set_mask(c, cam, one)


def huge_blob(c):
    m = np.zeros((H, W), np.uint8)
    cv2.ellipse(m, (W // 2, H // 2), (250, 190), 0, 0, 360, 255, -1)      # ~48 % of the image
    _set_mask(c, 1, m)


def huge_image(c):
    cv2.imwrite(str(c / "cam0.png"), cv2.resize(_mask(c / "cam0.png"), (W * 8, H * 8)))


def huge_camera(c):
    _edit(c, lambda d: d["cameras"][0].update(width=10 ** 6, height=10 ** 6))


def border_only(c):
    m = np.zeros((H, W), np.uint8)
    m[:3], m[-3:], m[:, :3], m[:, -3:] = 255, 255, 255, 255
    _set_mask(c, 0, m)


def nan_K(c):
    _edit(c, lambda d: d["cameras"][0]["K"][0].__setitem__(0, float("nan")))


def inf_t(c):
    _edit(c, lambda d: d["cameras"][1].update(t=[0.0, float("inf"), 0.6]))


def nan_R(c):
    _edit(c, lambda d: d["cameras"][1]["R"][2].__setitem__(2, float("nan")))


def inf_dist(c):
    _edit(c, lambda d: d["cameras"][0].update(dist=[float("inf"), 0, 0, 0, 0]))


def zero_width(c):
    _edit(c, lambda d: d["cameras"][0].update(width=0))


def zero_size_file(c):
    (c / "cam1.png").write_bytes(b"")


def not_an_image(c):
    (c / "cam1.png").write_text("this is not a PNG")


def float_size(c):
    _edit(c, lambda d: d["cameras"][0].update(width=640.0))


def huge_distortion(c):
    _edit(c, lambda d: d["cameras"][0].update(dist=[1e6, -1e9, 0, 0, 1e12]))


def tiny_focal(c):
    _edit(c, lambda d: d["cameras"][1]["K"][0].__setitem__(0, 1e-9))


def base_inside_camera(c):
    def put_base_at_camera(d):
        R, t = np.array(d["cameras"][0]["R"]), np.array(d["cameras"][0]["t"])
        d["tape"]["base"]["position"] = (-R.T @ t).tolist()
    _edit(c, put_base_at_camera)


CASES = {
    "random noise": (random_noise, "either"), "random blobs": (random_blobs, "either"),
    "empty": (empty, "refuse"), "full": (full, "refuse"), "inverted": (inverted, "refuse"),
    "one pixel": (one_pixel, "either"), "one pixel in both": (one_pixel_both, "either"),
    "huge blob": (huge_blob, "either"), "huge image": (huge_image, "refuse"), "huge camera": (huge_camera, "refuse"),
    "border only": (border_only, "either"),
    "NaN in K": (nan_K, "refuse"), "inf in t": (inf_t, "refuse"), "NaN in R": (nan_R, "refuse"),
    "inf in dist": (inf_dist, "refuse"), "zero width": (zero_width, "refuse"),
    "zero-size file": (zero_size_file, "refuse"), "not an image": (not_an_image, "refuse"),
    "float size": (float_size, "refuse"), "huge distortion": (huge_distortion, "either"),
    "tiny focal length": (tiny_focal, "either"), "tape base at a camera": (base_inside_camera, "either"),
}


@pytest.fixture(scope="module")
def broken(tmp_path_factory) -> dict[str, Path]:
    root = tmp_path_factory.mktemp("fuzz")
    good = save_capture(make_capture(20001, SyntheticOptions(kind="chain", cameras=2)), root / "good")
    out = {}
    for i, (name, (breaker, _)) in enumerate(CASES.items()):
        path = root / f"case{i:02d}"
        shutil.copytree(good, path)
        breaker(path)
        out[name] = path
    return out


def _tapecell(*args: str, timeout: float = 300) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "tapecell.cli.main", *args], capture_output=True, text=True,
                          timeout=timeout)


def test_every_broken_capture_is_refused_or_not_ok(broken, tmp_path):
    """All cases in one process (a crash in any is a negative return code and names it)."""
    names = list(broken)
    r = _tapecell("estimate", *[str(broken[n]) for n in names], "--out", str(tmp_path / "est"))
    assert r.returncode in (1, 2), f"exit {r.returncode} (a crash?):\n{r.stderr[-3000:]}"
    assert "Traceback" not in r.stderr, r.stderr
    lines = r.stderr.splitlines()
    problems = []
    for i, name in enumerate(names):
        folder = broken[name].name
        kind = CASES[name][1]
        errors = [l for l in lines if l.startswith(f"{folder} ") and " error: " in l]
        est_file = tmp_path / "est" / f"{folder}.json"
        if errors:
            if str(broken[name]) not in errors[0]:
                problems.append(f"{name}: the refusal does not name the capture's file: {errors[0]}")
            continue
        if kind == "refuse":
            problems.append(f"{name}: not refused")
        elif not est_file.exists():
            problems.append(f"{name}: neither refused nor estimated")
        elif json.loads(est_file.read_text())["verdict"] == "ok":
            problems.append(f"{name}: estimated with verdict ok")
    assert not problems, "\n".join(problems)


@pytest.mark.parametrize("name", ["full", "NaN in K", "zero-size file", "huge camera"])
def test_a_single_broken_capture_is_exit_2_and_one_line(broken, name):
    r = _tapecell("estimate", str(broken[name]))
    assert r.returncode == 2 and r.stdout == ""
    assert len(r.stderr.splitlines()) == 1 and r.stderr.startswith("tapecell: error: ")
    assert str(broken[name]) in r.stderr


# ------------------------------------------------------- garbage given to the estimator itself
KERNEL_FUZZ = r'''
import sys
import numpy as np
from tapecell.estimator import Camera, estimate
from tapecell.estimator.capture import Capture, View
from tapecell.estimator.errors import TapecellError
from tapecell.estimator.synthetic import SyntheticOptions, make_capture

good = make_capture(20002, SyntheticOptions(kind="chain", cameras=2))
H, W = good.views[0].mask.shape
rng = np.random.default_rng(20003)

def masks(kind, v):
    if kind == "full": return np.ones((H, W), bool)
    if kind == "noise": return rng.random((H, W)) < 0.5
    if kind == "inverted": return ~v.mask
    if kind == "one pixel":
        m = np.zeros((H, W), bool); m[H // 2, W // 2] = True; return m
    if kind == "corner pixel":
        m = np.zeros((H, W), bool); m[H - 1, W - 1] = True; return m
    if kind == "border":
        m = np.zeros((H, W), bool); m[0], m[-1], m[:, 0], m[:, -1] = True, True, True, True; return m
    raise ValueError(kind)

def camera(kind, c):
    if kind == "behind": return c.with_pose(c.R, -c.t)
    if kind == "far": return c.with_pose(c.R, c.t * 1e4)
    if kind == "tiny focal":
        K = c.K.copy(); K[0, 0] = K[1, 1] = 1e-6
        return Camera(c.name, c.width, c.height, K, c.dist, c.R, c.t)
    if kind == "wild distortion": return Camera(c.name, c.width, c.height, c.K, np.array([1e6, -1e9, 0, 0, 1e12]), c.R, c.t)
    if kind == "nan": return c.with_pose(c.R, np.array([np.nan, 0.0, 0.6]))
    raise ValueError(kind)

cases = [("mask", k) for k in ("full", "noise", "inverted", "one pixel", "corner pixel", "border")]
cases += [("camera", k) for k in ("behind", "far", "tiny focal", "wild distortion", "nan")]
name = sys.argv[1]
what, kind = next(c for c in cases if c[1] == name)
if what == "mask":
    views = [View(v.camera, masks(kind, v)) for v in good.views]
else:
    views = [View(camera(kind, v.camera), v.mask) for v in good.views]
cap = Capture(good.tape, views)
try:
    est = estimate(cap)
except TapecellError as e:
    print("refused:", e)
else:
    print("verdict:", est.verdict.value, est.verdict_reason)
'''

KERNEL_CASES = ["full", "noise", "inverted", "one pixel", "corner pixel", "border",
                "behind", "far", "tiny focal", "wild distortion", "nan"]


@pytest.mark.parametrize("case", KERNEL_CASES)
def test_the_estimator_never_crashes_on_garbage(case, tmp_path):
    """Inputs no loader would pass, given to estimate() directly: it refuses them
    (TapecellError) or returns an estimate whose verdict is not "ok"; it never crashes."""
    script = tmp_path / "fuzz.py"
    script.write_text(KERNEL_FUZZ)
    r = subprocess.run([sys.executable, str(script), case], capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, f"exit {r.returncode} (negative: killed by a signal)\n{r.stderr[-2000:]}"
    out = r.stdout.strip().splitlines()[-1]
    assert out.startswith("refused:") or (out.startswith("verdict:") and not out.startswith("verdict: ok")), out
