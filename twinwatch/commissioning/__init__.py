"""Commissioning: a machine's baseline parameters identified offline from a recording
(``twinwatch identify``), and what the recording can and cannot tell about them:
``identify`` (one structure), ``commission`` (the recording read, every structure identified,
the winner picked), ``report`` (text, Markdown) and ``record`` (the Rerun file). Its table,
``[identify]``, stands in :mod:`twinwatch.config.identify`. What it may import (never the
daemon, the outputs or the watcher; only the CLI imports it): docs/architecture.md.
"""
