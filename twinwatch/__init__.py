"""twinwatch: an interpretable digital-twin monitor for industrial machines.

Implements Vilar-Dias, Santos Junior and Lima-Neto, "An Interpretable Digital Twin for
Self-Aware Industrial Machines", Sensors 2024, 24(1):4.
"""

__version__ = "0.1.0"

from twinwatch import _kernels

_kernels.configure()
