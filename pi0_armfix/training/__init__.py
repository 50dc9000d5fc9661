"""Training machinery: mesh and sharding rules, optimizer, state and step, checkpoints, metrics."""
