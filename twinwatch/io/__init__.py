"""What sources and their consumers share, with no dependency on either: the sample type
(``sample``), the Modbus register map (``modbus_registers``), how a drive's controller runs
(``drive``), the sample counter (``counter``), the JSON encoder (``encoding``) and the Zenoh key
layout (``keys``); docs/architecture.md. ``twinwatch.plant``, ``twinwatch.drivers`` and the
twin's machines import from here, never from each other's internals. Imports nothing of
twinwatch but this room.
"""
