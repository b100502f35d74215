"""twinwatch.twin."""
