"""softbody: a differentiable soft-robot design and control workbench.

Importing ``softbody`` turns on JAX's 64-bit mode (``jax_enable_x64``): the simulator's
tolerances and the finite-difference gradient checks assume float64. Arrays you pass in
float32 are promoted; set ``JAX_ENABLE_X64=0`` *after* importing if you really want float32.

The distribution installs one namespace: ``softbody`` (the simulator),
``softbody.meshing`` (the repository's ``meshing/`` folder), ``softbody.actuators``
(``actuators/``) and ``softbody.control`` (``control/``).

Importing ``softbody`` also turns on JAX's persistent compilation cache in
``$SOFTBODY_CACHE_DIR/xla`` (default ``~/.cache/softbody/xla``), so later runs load the
programs they compiled before; ``SOFTBODY_COMPILATION_CACHE=0`` turns it off, and your own
``JAX_COMPILATION_CACHE_DIR`` wins (see :mod:`softbody.cache`).
"""

import jax

from softbody import cache as _cache

jax.config.update("jax_enable_x64", True)
_cache.setup()

__version__ = "0.1.0"
