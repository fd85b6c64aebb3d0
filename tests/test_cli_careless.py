"""A careless user: bad options, outputs that would replace or hide files, read-only and
missing folders, interrupted runs. Every case ends in exit 2 (or the documented code) and
one line, before any heavy work, and never loses or hides a user's file."""
from __future__ import annotations

import json
import os
import shutil
import signal
import stat
import subprocess
import sys
import tempfile
import time
import uuid
from pathlib import Path

import pytest

from tapecell import __version__
from tapecell.cli.main import main
from tapecell.estimator.capture import load_capture, save_capture
from tapecell.estimator.errors import OutputError
from tapecell.estimator.io import atomic_dir, atomic_write_json
from tapecell.estimator.synthetic import SyntheticOptions, make_capture


def _usage_error(argv, capsys) -> str:
    with pytest.raises(SystemExit) as e:
        main(argv)
    err = capsys.readouterr().err
    assert e.value.code == 2, err
    assert len(err.splitlines()) == 1 and "Traceback" not in err, err
    return err


def _error(argv, capsys, code: int = 2) -> str:
    rc = main([str(a) for a in argv])
    out, err = capsys.readouterr()
    assert rc == code, err
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("tapecell: error: "), err
    return lines[0]


@pytest.fixture(scope="module")
def capture(tmp_path_factory) -> Path:
    return save_capture(make_capture(20011, SyntheticOptions(kind="chain", cameras=2)),
                        tmp_path_factory.mktemp("c") / "cap")


@pytest.fixture
def readonly_dir(tmp_path) -> Path:
    """A folder where files cannot be created: a chmod'ed one, or (as root, who ignores
    permission bits) a sysfs folder."""
    if os.geteuid() != 0:
        d = tmp_path / "ro"
        d.mkdir()
        d.chmod(0o555)
        yield d
        d.chmod(0o755)
        return
    d = Path("/sys/kernel")
    probe = d / f"tapecell-test-{uuid.uuid4().hex[:8]}"
    try:
        probe.write_text("x")
    except OSError:
        yield d
        return
    probe.unlink()
    pytest.skip("no read-only folder available here")


# ---------------------------------------------------------------------- usage and help
def test_version_and_exit_codes_in_help(capsys):
    with pytest.raises(SystemExit) as e:
        main(["--version"])
    assert e.value.code == 0 and capsys.readouterr().out.strip() == f"tapecell {__version__}"
    with pytest.raises(SystemExit):
        main(["--help"])
    out = capsys.readouterr().out
    for code, words in (("0", "done"), ("1", "the task itself failed"), ("2", "bad input or usage"),
                        ("3", "the robot or other hardware failed")):
        assert f"  {code}  {words}" in out


@pytest.mark.parametrize("argv", [
    ["sim", "capture", "--out", "x", "--seed", "-1"], ["sim", "snapshot", "--out", "x", "--seed", "-1"],
    ["sim", "view", "--seed", "-1"], ["episode", "--seed", "-1"], ["episodes", "--n", "2", "--out", "x", "--seed", "-1"],
    ["calibrate", "--sim", "--out", "x.json", "--seed", "-1"], ["probe", "--sim", "--seed", "-1"],
    ["episode", "--seed", "99999999999"], ["episodes", "--n", "0", "--out", "x"], ["episodes", "--n", "2", "--out", "x",
                                                                                  "--jobs", "0"],
    ["sim", "capture", "--out", "x", "--cameras", "4"], ["estimate"], ["nonsense"],
])
def test_bad_options_are_one_line_and_exit_2(argv, capsys):
    err = _usage_error(argv, capsys)
    assert err.startswith("tapecell") and "error:" in err and "--help" in err


def test_seeds_run_past_the_last_one_are_refused(tmp_path, capsys):
    line = _error(["episodes", "--n", "5", "--seed", str(2 ** 32 - 3), "--out", tmp_path / "e"], capsys)
    assert "the last seed would pass" in line


# -------------------------------------------------------------- outputs that exist or fail
@pytest.mark.parametrize("argv, expected", [
    (["sim", "capture", "--out", "{file}"], "exists and is a file"),
    (["sim", "snapshot", "--out", "{file}"], "exists and is a file"),
    (["episodes", "--n", "1", "--out", "{file}"], "exists and is a file"),
    (["estimate", "{capture}", "--out", "{file}"], "exists and is a file"),
    (["sim", "cameras", "--out", "{file}"], "already exists"),
    (["calibrate", "--sim", "--out", "{file}"], "already exists"),
    (["probe", "--sim", "--out", "{file}"], "already exists"),
    (["episode", "--rrd", "{file}"], "already exists"),
    (["estimate", "{capture}", "--rrd", "{file}"], "already exists"),
    (["sim", "cameras", "--out", "{dir}"], "is a folder"),
])
def test_out_naming_an_existing_file_is_refused_before_any_work(argv, expected, tmp_path, capture, capsys):
    user_file = tmp_path / "precious.json"
    user_file.write_text("my calibration")
    folder = tmp_path / "folder"
    folder.mkdir()
    named = folder if "{dir}" in argv else user_file
    argv = [a.format(file=user_file, dir=folder, capture=capture) for a in argv]
    t0 = time.monotonic()
    line = _error(argv, capsys)
    assert expected in line and str(named) in line
    assert time.monotonic() - t0 < 5.0                          # refused before the simulation ran
    assert user_file.read_text() == "my calibration"


def test_force_replaces_an_existing_output_file(tmp_path, capsys):
    out = tmp_path / "cams.json"
    out.write_text("old")
    assert main(["sim", "cameras", "--out", str(out), "--force"]) == 0
    assert json.loads(out.read_text())["format"] == "tape-cameras/1"


@pytest.mark.parametrize("argv", [
    ["sim", "cameras", "--out", "{ro}/cams.json"],
    ["estimate", "{capture}", "--out", "{ro}/estimates"],
    ["estimate", "{capture}", "--rrd", "{ro}/fit.rrd"],
    ["calibrate", "--sim", "--out", "{ro}/cams.json"],
    ["episode", "--rrd", "{ro}/ep.rrd"],
    ["sim", "capture", "--out", "{ro}/cap"],
])
def test_out_in_a_read_only_folder_is_one_line(argv, readonly_dir, capture, capsys):
    argv = [a.format(ro=readonly_dir, capture=capture) for a in argv]
    line = _error(argv, capsys)
    assert "cannot write in" in line and str(readonly_dir) in line


def test_writing_into_a_read_only_folder_is_an_output_error(readonly_dir):
    with pytest.raises(OutputError, match="cannot"):
        atomic_write_json(readonly_dir / "x.json", {"a": 1})


@pytest.mark.parametrize("argv, expected", [
    (["estimate", "{tmp}/missing"], "capture directory not found"),
    (["calibrate", "--config", "{tmp}/missing.toml", "--out", "{tmp}/c.json"], "cell file not found"),
    (["episode", "--config", "{tmp}/missing.toml"], "cell file not found"),
    (["probe", "--config", "{tmp}/missing.toml", "--capture", "{tmp}/missing", "--execute"], "cell file not found"),
    (["run", "--config", "{cell}", "--cameras", "{tmp}/missing.json"], "file not found"),
])
def test_a_missing_file_or_folder_is_one_line(argv, expected, tmp_path, capsys):
    from tapecell.cell.config import default_cell_path

    argv = [a.format(tmp=tmp_path, cell=default_cell_path()) for a in argv]
    line = _error(argv, capsys)
    assert expected in line and "missing" in line


def test_out_in_a_missing_folder_is_created(tmp_path, capture, capsys):
    out = tmp_path / "new" / "deeper"
    assert main(["estimate", str(capture), "--out", str(out)]) == 0
    assert (out / "cap.json").exists()


# --------------------------------------------------------------- never lose or hide files
def test_two_captures_with_the_same_name_are_refused(tmp_path, capture, capsys):
    a, b = tmp_path / "a" / "cap", tmp_path / "b" / "cap"
    shutil.copytree(capture, a)
    shutil.copytree(capture, b)
    line = _error(["estimate", a, b, "--out", tmp_path / "est"], capsys)
    assert "same folder name 'cap'" in line and str(a) in line and str(b) in line
    assert not (tmp_path / "est").exists()
    line = _error(["estimate", a, a], capsys)
    assert "are the same capture" in line


def test_estimate_does_not_replace_an_estimate_without_force(tmp_path, capture, capsys):
    out = tmp_path / "est"
    out.mkdir()
    (out / "notes.txt").write_text("mine")
    assert main(["estimate", str(capture), "--out", str(out)]) == 0
    first = (out / "cap.json").read_text()
    capsys.readouterr()
    line = _error(["estimate", capture, "--out", out], capsys)
    assert "cap.json: already exists" in line and "--force" in line
    assert main(["estimate", str(capture), "--out", str(out), "--force"]) == 0
    assert json.loads((out / "cap.json").read_text())["format"] == json.loads(first)["format"]
    assert (out / "notes.txt").read_text() == "mine"


def test_sim_capture_keeps_a_users_files(tmp_path, capsys):
    out = tmp_path / "cap"
    out.mkdir()
    (out / "notes.txt").write_text("mine")
    (out / "cam0.png").write_text("not a capture")
    line = _error(["sim", "capture", "--out", out], capsys)
    assert "folder is not empty" in line and "--force" in line
    assert sorted(p.name for p in out.iterdir()) == ["cam0.png", "notes.txt"]
    assert main(["sim", "capture", "--out", str(out), "--force", "--seed", "20012"]) == 0
    names = sorted(p.name for p in out.iterdir())
    assert names == ["cam0.png", "cam1.png", "capture.json", "notes.txt", "truth.json"]   # nothing hidden
    assert (out / "notes.txt").read_text() == "mine" and load_capture(out).truth is not None


def test_atomic_dir_refuses_a_non_empty_folder_and_forced_keeps_others(tmp_path):
    out = tmp_path / "d"
    out.mkdir()
    (out / "keep").write_text("k")
    with pytest.raises(OutputError, match="not empty"):
        with atomic_dir(out) as tmp:
            (tmp / "new").write_text("n")
    assert [p.name for p in out.iterdir()] == ["keep"]
    with atomic_dir(out, force=True) as tmp:
        (tmp / "new").write_text("n")
    assert sorted(p.name for p in out.iterdir()) == ["keep", "new"]
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")]   # no temporary folder left
    with pytest.raises(RuntimeError):                                    # a failure writes nothing
        with atomic_dir(out, force=True) as tmp:
            (tmp / "half").write_text("h")
            raise RuntimeError("failed midway")
    assert sorted(p.name for p in out.iterdir()) == ["keep", "new"]


def test_a_forced_capture_without_truth_is_refused_over_an_old_truth(tmp_path):
    cap = make_capture(20013, SyntheticOptions(kind="chain", cameras=2))
    save_capture(cap, tmp_path / "c")
    import dataclasses
    with pytest.raises(OutputError, match="truth.json"):
        save_capture(dataclasses.replace(cap, truth=None), tmp_path / "c", force=True)


@pytest.mark.parametrize("umask", [0o022, 0o077, 0o002])
def test_files_get_the_users_umask(tmp_path, umask):
    old = os.umask(umask)
    try:
        atomic_write_json(tmp_path / "f.json", {"a": 1})
        save_capture(make_capture(20014, SyntheticOptions(kind="chain", cameras=2)), tmp_path / "cap")
        from tapecell.cell.recording import close_recording, open_recording
        close_recording(open_recording(tmp_path / "r.rrd"))
    finally:
        os.umask(old)
    for p in (tmp_path / "f.json", tmp_path / "cap" / "capture.json", tmp_path / "cap" / "cam0.png", tmp_path / "r.rrd"):
        assert stat.S_IMODE(p.stat().st_mode) == 0o666 & ~umask, p
    assert stat.S_IMODE((tmp_path / "cap").stat().st_mode) == 0o777 & ~umask


# ----------------------------------------------------------- a failed run leaves nothing
def test_a_failed_estimate_leaves_no_recording(tmp_path, capture, capsys):
    broken = tmp_path / "broken"
    shutil.copytree(capture, broken)
    (broken / "cam0.png").unlink()
    rrd = tmp_path / "out" / "fit.rrd"
    _error(["estimate", broken, "--rrd", rrd], capsys)
    assert not rrd.parent.exists() or list(rrd.parent.iterdir()) == []


def test_a_terminated_episode_leaves_no_recording(tmp_path):
    """SIGTERM mid-run: tapecell cleans up as for Ctrl-C (exit 143) and leaves no .tmp."""
    rrd = tmp_path / "ep.rrd"
    # The child's output goes to files, not pipes: a pipe nobody reads while the test waits
    # blocks the child once it fills (64 KB of warnings would stall the episode).
    with tempfile.TemporaryFile("w+") as out_file, tempfile.TemporaryFile("w+") as err_file:
        proc = subprocess.Popen([sys.executable, "-m", "tapecell.cli.main", "episode", "--seed", "20015", "--rrd",
                                 str(rrd)], stdout=out_file, stderr=err_file, text=True)
        try:
            deadline = time.monotonic() + 120
            while time.monotonic() < deadline and not any(tmp_path.iterdir()):
                time.sleep(0.05)                 # the hidden temporary recording appears
            if not any(tmp_path.iterdir()):
                ended = proc.poll()
                err_file.seek(0)
                why = "still running" if ended is None else f"exited {ended}"
                raise AssertionError(f"the episode never started its recording within 120 s ({why}): "
                                     f"{err_file.read()[-2000:]}")
            proc.send_signal(signal.SIGTERM)
            proc.wait(timeout=60)
        finally:
            proc.kill()
            proc.wait()
        err_file.seek(0)
        err = err_file.read()
    assert proc.returncode == 143, err
    assert err.strip().splitlines()[-1] == "tapecell: terminated"
    # Nothing half-written. (Where the signal lands in a finaliser, Python ignores its
    # exception and prints it; the episode then ends and its recording is whole.)
    assert not [p for p in tmp_path.iterdir() if p.name.endswith(".tmp")]
    assert "Traceback" not in err or "Exception ignored in" in err


def test_episodes_keep_a_users_folder_but_resume_their_own(tmp_path, capsys):
    out = tmp_path / "runs"
    out.mkdir()
    (out / "notes.txt").write_text("mine")
    line = _error(["episodes", "--n", "1", "--out", out], capsys)
    assert "folder is not empty" in line and "--force" in line
    assert [p.name for p in out.iterdir()] == ["notes.txt"]


def test_calibrate_checks_its_images_before_asking(tmp_path, monkeypatch, capsys):
    from tapecell.cell.config import default_cell_path

    monkeypatch.setattr("builtins.input", lambda prompt="": pytest.fail("asked before checking the images"))
    line = _error(["calibrate", "--config", default_cell_path(), "--out", tmp_path / "c.json", "--execute",
                   "--images", tmp_path / "missing"], capsys)
    assert "image folder not found" in line
