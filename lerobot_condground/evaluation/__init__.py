"""Evaluating policies: checkpoint loading, batched rollouts, the sweep's units and launchers, results and statistics."""
