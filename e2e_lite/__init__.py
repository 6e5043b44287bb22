"""e2e-lite: a CPU-sized teaching reproduction of "Closing the gap towards end-to-end autonomous
vehicle system" (Glassner et al., 2019) with its PilotNet baseline.

Layers, each importing only those above it in this list:
geometry -> vehicle -> world -> evaluation -> drivers -> viz; config and artifacts are used by all.
"""

__version__ = "0.1.0"
