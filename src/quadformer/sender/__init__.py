"""A test sender: a vehicle's sensor streams played as MAVLink, as an autopilot sends them, for
demos, tests and benchmarks of the live monitor.

``VehicleStreams`` (``streams``) holds what a vehicle would stream: a recorded log's sensors or a
simulated flight's, optionally with a spoof injected into its GPS; ``send`` (``play``) plays them
to a receiver over a pymavlink link, with the faults ``SenderConfig`` (``config``) asks for, and
returns a ``SendReport``; ``link`` is the sender's end of the link (the receiver's answers, the
packets as they left). The sender builds on the sensors' MAVLink messages (``sensors.mavlink``)
and connection (``sensors.mavlink_link``); the monitor (``quadformer.live``) never imports it.
"""

from quadformer.sender.config import FAULTY, SenderConfig, SendReport
from quadformer.sender.play import send
from quadformer.sender.streams import SIM_ORIGIN, VehicleStreams

__all__ = ["FAULTY", "SIM_ORIGIN", "SenderConfig", "SendReport", "VehicleStreams", "send"]
