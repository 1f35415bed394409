"""nanostage: experiment_runner."""
