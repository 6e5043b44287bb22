"""Learning to drive from the expert: the dataset and its collector, recovery views, models and
heads, losses (GMM, CVaR), training with checkpoints, the chapters' recipes and the agents that
turn a network into a driver. The models, losses and training import without the simulator."""
