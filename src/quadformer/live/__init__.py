"""A source of flights: a live MAVLink link.

MAVLink messages of a vehicle are decoded into timestamped samples (``mavlink``), checked and
put on the link's time base by the intake (``intake``; datagrams and packet loss: ``packets``)
and fed, one message at a time, to the very ``estimator.online.ResidueStream`` the log replay
drives, one segment of the vehicle's clock at a time (``segment``); each residue row is scored
by the detector's online stream, as ``quadformer detect`` does offline; alarms drive the
resilient GPS admission rule and its actions (``alerts``; the vehicle side and the records:
``actions``). The monitor (``monitor``; settings ``config``, the vehicle followed and its local
frame ``vehicle``, status line and summary ``status``) drives all of it from the link. A test
sender streams recorded or simulated sensors as MAVLink over UDP (``sender``; the streams
``vehicle_streams``, settings and report ``sender_config``, its end of the link ``sender_link``).
"""
