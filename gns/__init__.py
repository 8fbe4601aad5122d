"""Graph Network Simulator for rigid bodies (Allen et al., CoRL 2022): model, training, rollouts, metrics."""
