"""Stand-ins for ur_rtde's three modules that talk to a controller over a socket, as the
real ones do: every call is one JSON line to ``$TAPECELL_FAKE_UR`` (host:port) and waits
for one line back. A controller that goes silent blocks the call for ever (as ur_rtde
does); one that closes the connection makes the call raise RuntimeError (as ur_rtde does).
Used by tests/test_robot_deadlines.py through URArm's real ProcessLink (these folders are
put first on the link process's path)."""
import json
import os
import socket


class Interface:
    kind = ""

    def __init__(self, hostname, *args, **kwargs):
        host, port = os.environ["TAPECELL_FAKE_UR"].rsplit(":", 1)
        self._sock = socket.create_connection((host, int(port)))
        self._file = self._sock.makefile("rwb")
        self._call("__init__", self.kind, hostname)

    def _call(self, method, *args):
        try:
            self._file.write((json.dumps({"m": method, "a": list(args)}) + "\n").encode())
            self._file.flush()
            line = self._file.readline()
        except OSError as e:
            raise RuntimeError(f"RTDE connection lost ({e})") from None
        if not line:
            raise RuntimeError("RTDE connection lost (the controller closed it)")
        reply = json.loads(line)
        if "error" in reply:
            raise RuntimeError(reply["error"])
        return reply["r"]

    def __getattr__(self, name):
        if name.startswith("_"):
            raise AttributeError(name)
        return lambda *args: self._call(name, *args)

    def disconnect(self):
        try:
            self._call("disconnect")
        finally:
            self._sock.close()
