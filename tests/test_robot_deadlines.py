"""A robot that goes silent or drops the connection never hangs tapecell: every call has a
deadline; past it the arm is told to stop on channels of its own, the link is closed, and
the command exits with 3 and one line, within 15 s. Loopback servers only, all bounded.

* URArm with in-process fakes (ThreadLink): a move that never returns.
* URArm's real ProcessLink with socket stand-ins for ur_rtde (tests/net_rtde), driven by
  a fake controller here, through the whole ``tapecell calibrate --execute`` command in a
  subprocess: the controller goes silent at the first move, or closes the connection.
* The real ur_rtde constructor against a host that accepts and never answers (it hangs
  holding the GIL): the ProcessLink's deadline kills it.
"""
from __future__ import annotations

import json
import os
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from tapecell.cell.arm import ArmError
from tapecell.cell.config import GripperIOSection, default_cell_path
from tapecell.cell.kinematics import fk, ik_nearest
from tapecell.cell.poses import matrix_to_pose6, pose6_to_matrix
from tapecell.cell.safety import SafetyLimits
from tapecell.cell.ur import RobotSilent, URArm
from tapecell.cell.ur_link import LinkTimeout, ProcessLink
from fakes import FakeRobot, install_fake_rtde

NET_RTDE = Path(__file__).parent / "net_rtde"
Q_HOME = np.array([-1.5708, -1.5708, 1.5708, -1.5708, -1.5708, 0.0])
LIMITS = SafetyLimits(workspace_min=[-0.30, 0.10, 0.05], workspace_max=[0.60, 0.90, 0.70],
                      max_tcp_speed=0.25, max_tcp_accel=1.2, max_joint_speed=1.0,
                      keepout_min=[-0.07, 0.44, 0.0], keepout_max=[0.07, 0.56, 0.095])


class Listener:
    """Accepts connections on 127.0.0.1 and keeps what each sends (the stop channels);
    ``greeting`` is sent first (the dashboard server says hello)."""

    def __init__(self, greeting: bytes = b"") -> None:
        self.greeting, self.received = greeting, []
        self.sock = socket.socket()
        self.sock.bind(("127.0.0.1", 0))
        self.sock.listen(4)
        self.sock.settimeout(0.1)
        self.port = self.sock.getsockname()[1]
        self.stopping = False
        self.thread = threading.Thread(target=self._serve, daemon=True)
        self.thread.start()

    def _serve(self) -> None:
        while not self.stopping:
            try:
                conn, _ = self.sock.accept()
            except OSError:
                continue
            with conn:
                conn.settimeout(1.0)
                if self.greeting:
                    conn.sendall(self.greeting)
                data = b""
                try:
                    while chunk := conn.recv(256):
                        data += chunk
                except OSError:
                    pass
                self.received.append(data)

    def close(self) -> None:
        self.stopping = True
        self.thread.join(2)
        self.sock.close()


class Controller:
    """A fake UR controller for the socket stand-ins: answers each JSON call from its state
    (the nominal UR5e kinematics), and at the first call named in ``fail_on`` either goes
    silent (``mode="silent"``, the connection stays open) or closes the connection."""

    def __init__(self, q, mode: str, fail_on: str = "moveJ") -> None:
        self.q = np.array(q, float)
        self.mode, self.fail_on = mode, fail_on
        self.log: list[tuple[float, str]] = []
        self.failed_at: float | None = None
        self.sock = socket.socket()
        self.sock.bind(("127.0.0.1", 0))
        self.sock.listen(8)
        self.sock.settimeout(0.1)
        self.port = self.sock.getsockname()[1]
        self.conns: list[socket.socket] = []
        self.stopping = False
        threading.Thread(target=self._accept, daemon=True).start()

    def _accept(self) -> None:
        while not self.stopping:
            try:
                conn, _ = self.sock.accept()
            except OSError:
                continue
            self.conns.append(conn)
            threading.Thread(target=self._serve, args=(conn,), daemon=True).start()

    def _serve(self, conn: socket.socket) -> None:
        f = conn.makefile("rwb")
        try:
            for line in f:
                req = json.loads(line)
                m, a = req["m"], req["a"]
                self.log.append((time.monotonic(), m))
                if m == self.fail_on and self.failed_at is None:
                    self.failed_at = time.monotonic()
                    if self.mode == "close":
                        conn.shutdown(socket.SHUT_RDWR)
                        conn.close()
                        return
                if self.failed_at is not None and self.mode == "silent":
                    continue      # never answers again
                f.write((json.dumps({"r": self._answer(m, a)}) + "\n").encode())
                f.flush()
        except (OSError, ValueError):
            return

    def _answer(self, m: str, a: list):
        if m == "getActualQ":
            return self.q.tolist()
        if m == "getActualTCPPose":
            return matrix_to_pose6(fk(self.q)).tolist()
        if m == "getForwardKinematics":
            return matrix_to_pose6(fk(np.asarray(a[0]) if a and a[0] else self.q)).tolist()
        if m == "getInverseKinematics":
            return ik_nearest(pose6_to_matrix(a[0]), np.asarray(a[1])).tolist()
        if m == "moveJ":
            self.q = np.asarray(a[0], float)
        if m in ("isProtectiveStopped", "getDigitalInState"):
            return False
        return True

    def close(self) -> None:
        self.stopping = True
        for c in self.conns:
            c.close()
        self.sock.close()


@pytest.fixture
def stops():
    script, dashboard = Listener(), Listener(b"Connected: Universal Robots Dashboard Server\n")
    yield script, dashboard
    script.close()
    dashboard.close()


@pytest.fixture
def rtde_handshake():
    """Answers the RTDE protocol-version request, as a UR controller does (probe_rtde)."""
    from test_arm_ur import RTDEServer

    server = RTDEServer(answer=True)
    yield server
    server.close()


# ------------------------------------------------------------- in-process fakes, ThreadLink
def test_silent_move_stops_disconnects_and_raises_within_the_deadline(monkeypatch, stops, rtde_handshake):
    robot = FakeRobot(Q_HOME)
    install_fake_rtde(monkeypatch, robot)
    robot.move_blocks = threading.Event()          # the controller never answers a move
    script, dashboard = stops
    arm = URArm("127.0.0.1", rtde_handshake.port, LIMITS, gripper=GripperIOSection(close_wait_s=0, open_wait_s=0),
                move_margin_s=0.5, dashboard_port=dashboard.port, script_port=script.port)
    target = matrix_to_pose6(fk(Q_HOME)) + np.array([0.0, 0.0, -0.02, 0, 0, 0])
    try:
        arm.connect()
        t0 = time.monotonic()
        with pytest.raises(RobotSilent) as e:
            arm.move_linear(target, 0.1, 0.5)
        elapsed = time.monotonic() - t0
    finally:
        robot.move_blocks.set()                    # release the abandoned worker thread
    # moveL's deadline: 20 mm at 0.1 m/s + 0.1/0.5 s + 0.5 s margin = 0.9 s; then the stop.
    assert 0.8 < elapsed < 5.0
    msg = str(e.value)
    assert e.value.exit_code == 3 and "did not answer moveL" in msg and "within 0.9 s" in msg
    assert "sent URScript stopj and dashboard stop" in msg and msg.endswith("disconnected")
    time.sleep(0.3)
    assert script.received == [b"stopj(2.0)\n"] and dashboard.received == [b"stop\n"]
    assert not arm.is_connected
    with pytest.raises(ArmError):                  # nothing more goes to the silent robot
        arm.move_linear(target, 0.1, 0.5)


def test_a_silent_path_is_abandoned_after_its_deadline_with_the_script_upload(monkeypatch, stops, rtde_handshake):
    robot = FakeRobot(Q_HOME)
    install_fake_rtde(monkeypatch, robot)
    robot.move_blocks = threading.Event()
    script, dashboard = stops
    arm = URArm("127.0.0.1", rtde_handshake.port, LIMITS, gripper=GripperIOSection(close_wait_s=0, open_wait_s=0),
                move_margin_s=0.5, dashboard_port=dashboard.port, script_port=script.port)
    start = matrix_to_pose6(fk(Q_HOME))
    path = [start + np.array([0.0, 0.0, -0.01 * k, 0, 0, 0]) for k in (1, 2)]
    try:
        arm.connect()
        t0 = time.monotonic()
        with pytest.raises(RobotSilent) as e:
            arm.move_linear_path(path, 0.1, 0.5, 0.002)
        elapsed = time.monotonic() - t0
    finally:
        robot.move_blocks.set()
    # 20 mm at 0.1 m/s + 2 x 0.1/0.5 s + PATH_SCRIPT_S 2 s (ur_rtde uploads a script for a
    # path before it starts) + 0.5 s margin = 3.1 s; then the stop.
    assert 3.0 < elapsed < 7.0
    msg = str(e.value)
    assert "did not answer moveL path of 2 poses" in msg and "within 3.1 s" in msg
    time.sleep(0.3)
    assert script.received == [b"stopj(2.0)\n"] and dashboard.received == [b"stop\n"]


# ---------------------------------------------------- the real ProcessLink, the whole command
def _cell_file(tmp_path: Path, rtde_port: int, script_port: int, dashboard_port: int) -> Path:
    text = default_cell_path().read_text()
    text = text.replace('host = "192.168.1.10"', 'host = "127.0.0.1"')
    text = text.replace("port = 30004\n", f"port = {rtde_port}\ncall_timeout_s = 1.0\nmove_margin_s = 1.0\n"
                                          f"dashboard_port = {dashboard_port}\nscript_port = {script_port}\n")
    path = tmp_path / "cell.toml"
    path.write_text(text)
    return path


@pytest.mark.parametrize("mode", ["silent", "close"])
def test_calibrate_execute_against_a_robot_that_fails_mid_move(tmp_path, mode, stops, rtde_handshake):
    from tapecell.cell.config import load_cell_config

    script, dashboard = stops
    controller = Controller(load_cell_config().arm.home_joints, mode)
    cell = _cell_file(tmp_path, rtde_handshake.port, script.port, dashboard.port)
    (tmp_path / "images").mkdir()
    env = dict(os.environ, TAPECELL_FAKE_UR=f"127.0.0.1:{controller.port}",
               PYTHONPATH=os.pathsep.join([str(NET_RTDE), os.environ.get("PYTHONPATH", "")]))
    t0 = time.monotonic()
    try:
        r = subprocess.run([sys.executable, "-m", "tapecell.cli.main", "calibrate", "--config", str(cell),
                            "--out", str(tmp_path / "cams.json"), "--images", str(tmp_path / "images"),
                            "--execute", "--yes"], env=env, capture_output=True, text=True, timeout=60)
    finally:
        controller.close()
    end = time.monotonic()
    err_lines = [l for l in r.stderr.splitlines() if l.startswith("tapecell")]
    assert r.returncode == 3, r.stderr
    assert len(err_lines) == 1 and "Traceback" not in r.stderr, r.stderr
    assert controller.failed_at is not None and end - controller.failed_at < 15.0
    names = [m for _, m in controller.log]
    assert names.index("getForwardKinematics") < names.index("moveJ")      # checked before moving
    line = err_lines[0]
    if mode == "silent":
        assert "did not answer moveJ to" in line
    else:
        assert "moveJ to" in line and "failed: RTDE connection lost" in line
    assert "sent URScript stopj and dashboard stop" in line
    assert b"stopj(2.0)\n" in script.received and b"stop\n" in dashboard.received
    assert not (tmp_path / "cams.json").exists()
    assert end - t0 < 40


# ---------------------------------------------- the real ur_rtde constructor, a silent host
def test_real_ur_rtde_constructor_on_a_silent_host_is_killed_at_the_deadline():
    pytest.importorskip("rtde_receive")
    silent = socket.socket()
    silent.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    try:
        silent.bind(("127.0.0.1", 30004))      # ur_rtde always connects to port 30004
    except OSError:
        pytest.skip("port 30004 is in use here")
    silent.listen(8)
    link = ProcessLink()
    t0 = time.monotonic()
    try:
        with pytest.raises(LinkTimeout):
            link.open("127.0.0.1", timeout=3.0)
        assert time.monotonic() - t0 < 8.0      # spawn + 3 s deadline + kill
        assert link.dead and not link._proc.is_alive()
    finally:
        link.kill()
        silent.close()


def test_a_host_that_accepts_and_never_answers_is_exit_3_within_15_s(tmp_path, stops, capsys):
    """Before any ur_rtde constructor runs, the RTDE handshake is probed with a deadline."""
    from tapecell.cli.main import main
    from test_arm_ur import RTDEServer

    silent = RTDEServer(answer=False)
    script, dashboard = stops
    cell = _cell_file(tmp_path, silent.port, script.port, dashboard.port)
    (tmp_path / "images").mkdir()
    t0 = time.monotonic()
    try:
        code = main(["calibrate", "--config", str(cell), "--out", str(tmp_path / "cams.json"),
                     "--images", str(tmp_path / "images"), "--execute", "--yes"])
    finally:
        silent.close()
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 3 and time.monotonic() - t0 < 15.0
    assert err[-1].startswith("tapecell: error: cannot connect to the UR arm at 127.0.0.1")
    assert "did not answer the RTDE handshake" in err[-1]
    assert sum(l.startswith("tapecell") for l in err) == 1
