"""The twin: the white-box model of the machine, how it is fitted to each window, and what it says.

Rooms, from the ground up (``tests/test_layering.py`` holds the rules):

``model.py``
    The model contract (:class:`~twinwatch.twin.model.TwinModel`, :class:`WindowData`,
    parameter and output specs, the exact sub-step composition). Imports nothing of twinwatch.
``models/``
    The machines (DC motor, PWM DC motor, hydraulic actuator), their compiled kernels and the
    model registry. Import the contract and the drive description (:mod:`twinwatch.io.drive`);
    never the estimation or the discovery.
``estimation/``
    The estimator as stages (global search, polish, identifiability gate, model check,
    fusion), the fitting core, the residual statistics, commissioning (``identify``). Imports
    the contract only: it estimates any model.
``discovery/``
    The search for what the model lacks: meta-models (paper Table 1 and beyond), terms, the
    forward selection. Imports the contract and the estimation.
``adaptation.py``, ``health.py``
    The top: one window's adaptation (estimation, re-validation, discovery) and the health
    message it produces. What the daemon and the sinks may import of the twin.
"""
