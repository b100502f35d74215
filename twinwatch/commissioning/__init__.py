"""Commissioning: a machine's baseline parameters identified offline from a recording
(``twinwatch identify``), and what the recording can and cannot tell about them.

* ``identify``: the identification of one model structure (the long free-run fit, the
  identifiability analysis, the hold-and-refit, the scores on the validation range, the
  information criteria), the comparison of candidate structures and the
  ``[machine.parameters]`` block to paste;
* ``commission``: the recording read through the configured driver, every structure
  identified, the winner picked;
* ``report``: the result as text and as Markdown tables;
* ``record``: the result as a Rerun file (MATLAB's ``compare`` and ``resid``).

Its table, ``[identify]``, stands in :mod:`twinwatch.config.identify` (the configuration
validates it; this room stands above the configuration).

May import: the ground, :mod:`twinwatch.io`, :mod:`twinwatch.config`,
:mod:`twinwatch.drivers` (the recording is read through the configured driver), the model
contract, the machines (:mod:`twinwatch.twin.models`) and the estimation. Never the daemon,
the outputs (:mod:`twinwatch.sinks`) or the watcher: commissioning runs once, offline, beside
the service. Only the CLI imports it.
"""
