"""What sources and their consumers share, with no dependency on either (docs/architecture.md).
``twinwatch.plant``, ``twinwatch.drivers`` and the
twin's machines import from here, never from each other's internals. Imports nothing of
twinwatch but this room.
"""
