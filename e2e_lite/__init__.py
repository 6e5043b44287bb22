"""e2e-lite: a CPU-sized teaching reproduction of "Closing the gap towards end-to-end autonomous
vehicle system" (Glassner et al., 2019) with its PilotNet baseline.

The folders are the layers, bottom to top; a module imports from its own folder and those below
(tests/test_layers.py): stats -> simulation -> learning -> control -> driving -> imitation ->
safety -> course -> record -> exercises. ``config`` and ``artifacts`` are used by all.
"""

__version__ = "0.1.0"
