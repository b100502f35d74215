"""twinwatch.plant."""
