"""What sources and their consumers share, with no dependency on either: the sample type
(``sample``), the Modbus register map (``modbus_registers``), how a drive's controller runs
(``drive``), the sample counter (``counter``), the JSON encoder (``encoding``), the Zenoh key
layout (``keys``) and a library's records from a source's thread at DEBUG (``threadlog``);
docs/architecture.md. ``twinwatch.plant``, ``twinwatch.drivers`` and the
twin's machines import from here, never from each other's internals. Imports nothing of
twinwatch but this room.
"""
