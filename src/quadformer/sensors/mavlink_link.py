"""A MAVLink connection, the live monitor's and the test sender's: a pymavlink connection that
speaks MAVLink 2 with the ardupilotmega dialect and parses robustly, and the address it is bound
to. The messages' conversions to samples are ``sensors.mavlink``'s."""

from __future__ import annotations

import socket

from pymavlink import mavutil

from quadformer.sensors.mavlink import mavlink2

__all__ = ["local_address", "open_link"]


# -- the link -------------------------------------------------------------------------------
def open_link(device: str, source_system: int = 255, source_component: int = 191, baud: int = 115200,
              rcvbuf: int = 1 << 20):
    """A pymavlink connection (any string pymavlink accepts: ``udpin:HOST:PORT``,
    ``udpout:HOST:PORT``, ``tcp:HOST:PORT``, ``tcpin:HOST:PORT``, a serial device, also as
    ``DEVICE,BAUD`` as MAVProxy writes it) that speaks
    MAVLink 2 with the ardupilotmega dialect from its first byte (parsing MAVLink 1 too),
    whatever pymavlink's process-wide default, and keeps messages with a bad CRC as
    ``BAD_DATA`` (robust parsing). A UDP socket's receive buffer is raised to ``rcvbuf``
    bytes where the system allows (bursts of a fast stream are not dropped by the kernel)."""
    if ":" not in device and "," in device:
        device, rate = device.rsplit(",", 1)
        baud = int(rate)
    conn = mavutil.mavlink_connection(device, baud=baud, source_system=source_system,
                                      source_component=source_component, autoreconnect=False)
    conn.mav = mavlink2.MAVLink(conn, srcSystem=source_system, srcComponent=source_component)
    conn.mav.robust_parsing = True
    conn.robust_parsing = True
    conn.WIRE_PROTOCOL_VERSION = "2.0"
    conn.first_byte = False           # no switch of pymavlink's global dialect on the first packet
    sock = getattr(conn, "port", None)
    if isinstance(sock, socket.socket) and sock.type == socket.SOCK_DGRAM:
        try:
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, rcvbuf)
        except OSError:
            pass
    return conn


def local_address(conn) -> tuple[str, int] | None:
    """(host, port) a UDP or TCP connection is bound to (an ephemeral port once known)."""
    sock = getattr(conn, "port", None) or getattr(conn, "listen_sock", None)
    try:
        return sock.getsockname() if sock is not None and hasattr(sock, "getsockname") else None
    except OSError:
        return None
