"""nanostage: stage_sim."""
from stage_sim import _cache  # noqa: F401  (numba's cache keyed by the compiled code: before any kernel)
