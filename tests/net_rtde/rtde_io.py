"""Socket stand-in for ur_rtde's rtde_io (see _client.py)."""
from _client import Interface


class RTDEIOInterface(Interface):
    kind = "io"
