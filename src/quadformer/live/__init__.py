"""A source of flights: a live MAVLink link.

MAVLink messages of a vehicle, read from a connection (``sensors.mavlink_link``), are decoded
into timestamped samples (``sensors.mavlink``), checked and put on the link's time base by the
intake (``intake``; datagrams and packet loss: ``packets``) and fed, one message at a time, to
the very ``estimator.online.ResidueStream`` the log replay drives, one segment of the vehicle's
clock at a time (``segment``); each residue row is scored by the detector's online stream, as
``quadformer detect`` does offline; alarms drive the resilient GPS admission rule and its
actions (``alerts``; the vehicle side and the records: ``actions``). The monitor (``monitor``;
settings ``config``, the vehicle followed and its local frame ``vehicle``, status line and
summary ``status``) drives all of it from the link. The test sender that streams recorded or
simulated sensors to it is ``quadformer.sender``.
"""
