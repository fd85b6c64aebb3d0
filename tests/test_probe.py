"""Probing: needle contact in simulation, and the real cell's freedrive path with ur_rtde faked."""
import json

import numpy as np
import pytest

from tapecell.cli.main import main
from tapecell.cell.kinematics import fk
from tapecell.cell.poses import pose6_to_matrix
from tapecell.cell.probe import PROBE_LABELS, ProbeError, guided_probe
from fakes import FakeRobot, install_fake_rtde
from tapecell.cell.config import load_cell_config


def test_probe_sim_measures_the_true_tip():
    from tapecell.cli.commands.probe import probe_sim

    lines = []
    result = probe_sim(load_cell_config(), seed=1, n_cameras=2, log=lines.append)
    assert [p.label for p in result["points"]] == list(PROBE_LABELS)
    # The needle stops on the tape's surface: within half the thickness (+ the arm's settling).
    assert max(result["e_truth"].values()) < 0.2e-3
    # e (eq. 12) of a reasonable estimate is millimetres at most, and not zero.
    assert all(0 < v < 0.01 for v in result["e_estimate"].values())
    assert any("eq. 12" in l for l in lines)


def test_a_side_where_the_needle_would_start_inside_the_tape_is_refused_before_any_move():
    """The simulated needle knows its distance to the tape: where its standoff would put it
    through the tape already, that side is refused without moving the arm or passing time
    (the move there and back cost two wrist flips per probe), the simulation left exactly as
    it was; from the free side it approaches fast, then slowly, and stops on the surface."""
    from tapecell.cell.probe import approach_normal, tape_points
    from tapecell.sim.arm import SimArm
    from tapecell.sim.cell import SimCell
    from tapecell.sim.prober import SimProber

    cfg = load_cell_config()
    with SimCell(cfg, seed=1, n_cameras=2, tool="needle") as sim:
        arm = SimArm(sim, tool="needle")
        prober = SimProber(sim, arm)
        tip = sim.tape_tip_frame()
        target = tape_points(tip[:3, 3], tip[:3, :3], cfg.tape.width, prober.params.inset)["tip"]
        normal = approach_normal(target, tip[:3, 2], -target)
        # Aimed 20 mm beyond the tape along the approach: the standoff is the tape itself.
        before = (sim.data.time, sim.data.qpos.copy(), sim.data.xpos.copy())
        with pytest.raises(ProbeError, match="meets the tape at its standoff"):
            prober.probe("through", target - prober.params.standoff * normal, normal)
        assert sim.data.time == before[0]
        assert np.array_equal(sim.data.qpos, before[1]) and np.array_equal(sim.data.xpos, before[2])
        measured = prober.probe("tip", target, normal).position
        assert np.linalg.norm(measured - target) < 0.2e-3
        steps = []
        sim.step_hook = lambda: steps.append(1)
        again = prober.probe("tip again", target, normal).position   # from the same standoff
        assert np.linalg.norm(again - measured) < 0.05e-3
        # The approach (20 mm) and the back-off: 20 mm at 10 mm/s alone would be 2,000 steps.
        assert len(steps) < 1500, len(steps)


# ------------------------------------------------------------------ real cell, ur_rtde faked
Q = np.array([1.2, -1.7, 1.9, -1.6, -1.5708, 0.3])


@pytest.fixture
def rtde_log(monkeypatch):
    robot = FakeRobot(Q, log_reads=True)
    install_fake_rtde(monkeypatch, robot, probe=False)
    return robot.log


@pytest.fixture
def capture_dir(tmp_path):
    d = tmp_path / "cap"
    d.mkdir()
    return d


def _run_real(monkeypatch, capture_dir, answers, execute=True, log=None):
    """Run ``probe --execute`` on a terminal; the first answer confirms (given before any
    connection: checked against ``log``), the others are the freedrive prompts."""
    it = iter((["yes"] if execute else []) + list(answers))

    def fake_input(prompt=""):
        if "Type 'yes'" in prompt:
            assert "192.168.1.10:30004" in prompt and (log is None or log == [])
        a = next(it)
        if isinstance(a, BaseException):
            raise a
        return a

    monkeypatch.setattr("builtins.input", fake_input)
    monkeypatch.setattr("sys.stdin.isatty", lambda: True)
    argv = ["probe", "--config", load_cell_config().source, "--capture", str(capture_dir)]
    return main(argv + (["--execute"] if execute else []))


def test_real_probe_records_needle_tip_in_freedrive(monkeypatch, rtde_log, capture_dir):
    assert _run_real(monkeypatch, capture_dir, ["", "", "s"], log=rtde_log) == 0
    names = [c[0] for c in rtde_log]
    assert names.index("teachMode") < names.index("getActualTCPPose") < names.index("endTeachMode")
    assert names.count("teachMode") == 1 and names.count("endTeachMode") == 1
    assert not {"moveL", "moveJ"} & set(names)                       # freedrive only, no motion
    doc = json.loads((capture_dir / "probe.json").read_text())
    assert doc["format"] == "tape-truth/1" and [p["label"] for p in doc["probed"]] == ["tip", "tip_left"]
    needle = pose6_to_matrix(load_cell_config().tools.needle.flange_from_tcp)
    expected = (fk(Q) @ needle)[:3, 3]
    assert np.allclose(doc["tip"]["position"], expected, atol=1e-9)


@pytest.mark.parametrize("failure", [KeyboardInterrupt(), RuntimeError("camera cable pulled")])
def test_real_probe_ends_teach_mode_on_interrupt_and_error(monkeypatch, rtde_log, capture_dir, failure):
    if isinstance(failure, KeyboardInterrupt):
        assert _run_real(monkeypatch, capture_dir, ["", failure]) == 130
    else:
        with pytest.raises(RuntimeError):
            _run_real(monkeypatch, capture_dir, ["", failure])
    names = [c[0] for c in rtde_log]
    assert names.count("teachMode") == 1 and names.count("endTeachMode") == 1
    assert names.index("endTeachMode") > names.index("teachMode")
    assert not (capture_dir / "probe.json").exists()


def test_real_probe_without_execute_connects_nothing(monkeypatch, rtde_log, capture_dir, capsys):
    assert _run_real(monkeypatch, capture_dir, [], execute=False) == 0
    assert rtde_log == [] and "nothing connected" in capsys.readouterr().out
    assert not (capture_dir / "probe.json").exists()


def test_guided_probe_with_nothing_recorded_is_an_error():
    from tapecell.cell.fake_arm import FakeArm

    arm = FakeArm()
    with arm:
        with pytest.raises(ProbeError):
            guided_probe(arm, [0, 0, 0.12, 0, 0, 0], PROBE_LABELS, prompt=lambda _: "q", log=lambda _: None)
        assert arm.freedrive_on is False
    assert [c for c in arm.calls if c[0] == "freedrive"] == [("freedrive", (True,)), ("freedrive", (False,))]


def test_real_probe_without_a_terminal_connects_nothing(monkeypatch, rtde_log, capture_dir, capsys):
    monkeypatch.setattr("sys.stdin.isatty", lambda: False)
    code = main(["probe", "--config", load_cell_config().source, "--capture", str(capture_dir), "--execute"])
    err = capsys.readouterr().err
    assert code == 2 and rtde_log == []
    assert "192.168.1.10:30004" in err and "freedrive" in err                 # what it would have done
    assert err.strip().splitlines()[-1].startswith("tapecell: error: --execute asks for a typed confirmation")


def test_real_probe_declined_connects_nothing(monkeypatch, rtde_log, capture_dir, capsys):
    monkeypatch.setattr("sys.stdin.isatty", lambda: True)
    monkeypatch.setattr("builtins.input", lambda prompt="": "no")
    code = main(["probe", "--config", load_cell_config().source, "--capture", str(capture_dir), "--execute"])
    assert code == 1 and rtde_log == [] and "cancelled" in capsys.readouterr().err


def test_the_needle_confirms_one_hypothesis_only_when_it_alone_touches_tape():
    """cell.probe.confirmed: the closest hypothesis within 4 mm, clearly closer than the rest,
    and no other within 4 mm; two tips that both touch tape are not told apart by which is
    closer (an episode kept one 0.8 mm from tape over one 2.3 mm away, 28 mm from the end)."""
    from tapecell.cell.probe import confirmed

    assert confirmed([0.0008, None]) == 0
    assert confirmed([0.0050, 0.0009]) == 1
    assert confirmed([0.0008, 0.0050]) == 0
    assert confirmed([0.0050, None]) is None              # nothing touched near enough
    assert confirmed([0.0023, 0.0008]) is None            # both on tape: the needle must look elsewhere
    assert confirmed([0.0030, 0.0042]) is None            # not clearly closer
    assert confirmed([None, None]) is None and confirmed([]) is None


def test_after_inconclusive_probes_only_a_clearly_closest_touched_tip_is_kept():
    """cell.probe.clearly_closest (the episode's last resort when several hypotheses' tips
    touch tape and probing where the shapes disagree tells nothing): the closest within 4 mm
    with every other at least 2.5 mm farther; right ones were kept at 2.6-3.4 mm, a wrong one
    28 mm from the end at 1.5 mm."""
    from tapecell.cell.probe import clearly_closest

    assert clearly_closest([0.00034, None, 0.00306]) == 0
    assert clearly_closest([0.0023, 0.0008]) is None            # 1.5 mm apart: not clear
    assert clearly_closest([0.0007, 0.00075]) is None
    assert clearly_closest([0.0050, 0.0090]) is None            # nothing within 4 mm
    assert clearly_closest([None, 0.0010]) == 1


@pytest.mark.parametrize("back_mm, off_mm, passes", [(12.0, 0.0, True), (12.0, 6.5, True), (12.0, 8.0, False),
                                                     (8.0, 4.0, True), (8.0, 6.0, False), (16.0, 9.0, True),
                                                     (2.0, 0.0, False), (30.0, 0.0, False)])
def test_the_trunk_touch_must_lie_on_the_ends_trunk_where_the_pads_hold_it(back_mm, off_mm, passes):
    """6-18 mm back along the end's trunk, bent off it by at most atan(7 / 12) (30 deg)
    wherever it was touched (a 38 deg bend touched 8 mm back, only 5 mm off, is refused)."""
    from tapecell.cell.probe import trunk_touch_problem

    R = np.array([[0.0, 0, 1], [0, 1, 0], [-1, 0, 0]])       # trunk -z, left +y, normal +x
    tip = np.array([0.1, 0.5, 0.08])
    touched = tip - 1e-3 * back_mm * R[:, 0] + 1e-3 * off_mm * R[:, 2]
    problem = trunk_touch_problem(tip, R, touched)
    assert (problem is None) == passes
    if not passes:
        assert "back from the end" in problem
        assert ("deg bend" in problem) == (6.0 <= back_mm <= 18.0)
