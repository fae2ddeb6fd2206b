"""The GCD engine: pure numpy, no model, no middleware."""

from gcdtrav.service.engine.gcd import MixtureStatistics, max_mixture_std, mixture_statistics
from gcdtrav.service.engine.maps import TraversabilityMaps, compute_maps

__all__ = ["MixtureStatistics", "TraversabilityMaps", "compute_maps", "max_mixture_std", "mixture_statistics"]
