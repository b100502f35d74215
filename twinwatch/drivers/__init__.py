"""twinwatch.drivers."""
