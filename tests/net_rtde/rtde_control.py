"""Socket stand-in for ur_rtde's rtde_control (see _client.py)."""
from _client import Interface


class RTDEControlInterface(Interface):
    kind = "control"
