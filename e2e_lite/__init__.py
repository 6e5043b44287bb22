"""e2e-lite: a CPU-sized teaching reproduction of "Closing the gap towards end-to-end autonomous
vehicle system" (Glassner et al., 2019) with its PilotNet baseline.

The folders are the layers, bottom to top; a module imports from its own folder and those below:
stats -> simulation -> control -> driving -> learning -> safety. ``config`` and ``artifacts`` are
used by all; ``ablation`` (chapter 10's harness), ``report``, ``viz``, ``course`` and ``bench`` sit beside
the layers and may import any of them.
"""

__version__ = "0.1.0"
