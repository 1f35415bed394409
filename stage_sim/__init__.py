"""nanostage: stage_sim."""
