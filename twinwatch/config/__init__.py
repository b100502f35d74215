"""twinwatch.config."""
