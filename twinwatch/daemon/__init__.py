"""twinwatch.daemon."""
