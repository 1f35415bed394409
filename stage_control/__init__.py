"""nanostage: stage_control."""
