"""nanostage: msg_defs."""
