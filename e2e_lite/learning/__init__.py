"""What learns, with no simulator in it: the label format (:mod:`.labels`), the dataset's schema
and container, the heads and models, the losses (GMM, CVaR), training with its checkpoints,
held-out measures and probes. It imports nothing from the simulation, control or driving layers
(tests/test_layers.py); what drives the simulator to learn is :mod:`e2e_lite.imitation`."""
