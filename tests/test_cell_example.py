"""assets/cell.example.toml: a complete, commented cell file for a real cell. It loads, it
ships with the package, and the real arm's gripper is driven from its [robot.gripper]."""
from __future__ import annotations

import fnmatch
import tomllib
from pathlib import Path

import numpy as np
import pytest

from tapecell.assets import asset_path
from tapecell.cell.config import CellConfigError, load_cell_config
from tapecell.cell.ur import URArm
from fakes import FakeRobot, install_fake_rtde

EXAMPLE = asset_path("cell.example.toml")


def test_the_example_loads_with_a_real_cells_settings():
    cfg = load_cell_config(EXAMPLE)
    r = cfg.robot
    assert r.host and r.port == 30004 and len(r.camera_devices) == len(cfg.cameras.camera)
    g = r.gripper
    assert (g.output_kind, g.close_output, g.open_output, g.closed_input) == ("standard", 0, 1, 2)
    assert g.close_wait_s > 0 and g.open_wait_s > 0
    assert np.all(np.asarray(cfg.limits.keepout_max) > np.asarray(cfg.limits.keepout_min))
    text = EXAMPLE.read_text()
    for section in ("[robot]", "[robot.gripper]", "[limits]", "[part]", "[cameras]"):
        assert section in text
    assert text.count("#") > 80                        # commented throughout


def test_the_example_is_package_data():
    pyproject = Path(__file__).resolve().parents[1] / "pyproject.toml"
    patterns = tomllib.loads(pyproject.read_text())["tool"]["setuptools"]["package-data"]["tapecell.assets"]
    assert any(fnmatch.fnmatch(EXAMPLE.name, p) for p in patterns)


def test_the_gripper_is_driven_as_the_cell_file_says(monkeypatch):
    cfg = load_cell_config(EXAMPLE)
    robot = FakeRobot(cfg.arm.home_joints)
    robot.close_sets_input = cfg.robot.gripper.closed_input     # the reed switch follows output 0
    install_fake_rtde(monkeypatch, robot, probe=False)
    waits = []
    with URArm.from_config(cfg, cfg.tools.gripper.flange_from_tcp, sleep=waits.append) as arm:
        arm.close_gripper()
        arm.open_gripper()
    io = [c for c in robot.log if c[0] in ("setStandardDigitalOut", "getDigitalInState")]
    assert io == [("setStandardDigitalOut", 1, False), ("setStandardDigitalOut", 0, True), ("getDigitalInState", 2),
                  ("setStandardDigitalOut", 0, False), ("setStandardDigitalOut", 1, True), ("getDigitalInState", 2)]
    assert waits == [0.4, 0.4]


@pytest.mark.parametrize("edit, key", [
    ("close_output = 0", "close_output = 9"), ("open_output = 1", "open_output = 0"),
    ("closed_input = 2 ", "closed_input = 12 "), ('output_kind = "standard"', 'output_kind = "wireless"'),
])
def test_a_wrong_gripper_wiring_is_one_clear_error(tmp_path, edit, key):
    bad = tmp_path / "cell.toml"
    bad.write_text(EXAMPLE.read_text().replace(edit, key, 1))
    with pytest.raises(CellConfigError, match=r"robot\.gripper\.") as e:
        load_cell_config(bad)
    assert str(bad) in str(e.value)
