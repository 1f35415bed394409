"""nanostage: stage_sim."""
from stage_sim import numba_cache  # noqa: F401  (numba's cache keyed by the compiled code: before any kernel)
