"""Helpers the test modules share. A test module imports from here (or from ``harness``, what
the benchmarks share too), never from another test module:

* :mod:`.paths`: the repository, the shared data beside it;
* :mod:`.plant`: the simulated motor's windows, for twin-level tests;
* :mod:`.twin`: drive descriptions and estimation settings several twin tests use;
* :mod:`.net`: free ports, Zenoh sessions and routers on loopback, waiting for a condition;
* :mod:`.cli`: the command line in this process or as a subprocess, machine configurations;
* :mod:`.fleet`: health messages and fleet summaries as daemons publish them;
* :mod:`.mqtt`, :mod:`.sparkplug`: a real Mosquitto, subscribers and a Sparkplug host decoder;
* :mod:`.recording`: a Rerun recorder on made-up windows and the ``rerun`` CLI;
* :mod:`.plugins`: a third-party driver's source, installed by the plug-in tests.
"""
