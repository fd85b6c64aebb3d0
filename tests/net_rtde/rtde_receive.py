"""Socket stand-in for ur_rtde's rtde_receive (see _client.py)."""
from _client import Interface


class RTDEReceiveInterface(Interface):
    kind = "receive"
