"""jaxdistill: intrinsic image distillation in JAX.

Distils per-photo opinions of an intrinsic-image diffusion model (RGB<->X) into
multi-view-consistent PBR texture maps (albedo, normal, roughness, metallic,
irradiance) for a room mesh seen from posed photos.
"""

from jaxdistill import xla_flags as _xla_flags

_xla_flags.apply()      # before JAX starts its backends (xla_flags.py says which flags, and why)

__version__ = "0.1.0"

MAP_NAMES = ("albedo", "normal", "roughness", "metallic", "irradiance")
"""The PBR maps the method reconstructs; also the only valid per-view target names."""
