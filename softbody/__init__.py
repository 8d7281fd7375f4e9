"""softbody: a differentiable soft-robot design and control workbench.

``import softbody as sb`` gives the chosen flat namespace (loaded on first use, so
``import softbody`` stays quick)::

    mesh = sb.meshing.examples.cantilever(size=0.01)
    model, params = sb.build(sb.SoftBody(mesh, sb.Material(E=1e5, nu=0.45), fixed="fixed"),
                             options=sb.Options(dt=0.01))
    traj = sb.rollout(model, params, sb.initial_state(model, params), n_steps=50)

Scenes: :func:`build`, :class:`SoftBody`, :class:`RigidBody`, :func:`prepare`, :func:`initial_state`,
:class:`Material`, :class:`Skeleton`, :class:`Fix` (vertices held in chosen components),
:class:`Membrane` (a membrane term on triangles, e.g. fabric bonded to a body),
:class:`Bending` (quadratic bending of a sheet), :func:`shell_body` (cloth and thin shells
alone: a body of triangles, no tets), :class:`Drag` (air drag and wind on triangles),
:class:`Options`, :class:`Model`, :class:`Params`, :class:`State`, :class:`SceneError`. A
scene owns its physics: ``build([SoftBody(mesh, material, fixed=..., actuators=[...]), ...],
skeleton=..., obstacles=[...])`` composes the step (the skeleton's reduced
coordinates, contact where there are obstacles); the options choose only numerics.
Stepping: :func:`rollout`, :func:`step`, :func:`solve_static`, :class:`Trajectory`,
:class:`StepInfo`, :class:`SimulationError`; integrators :class:`ImplicitEuler` (default)
and :class:`BDF2` (``Options(integrator=sb.BDF2())``). Strategies: :class:`LBFGS`,
:class:`LocalGlobal` (nonlinear solvers, ``Options(solver=...)``), :class:`Contact` (the
contact solver's settings, ``Options(contact=...)``), :class:`Implicit`, :class:`ImplicitForward`,
:class:`Unrolled` (differentiation), :func:`check_grad`. Parts by module:
``sb.meshing`` (geometry -> meshes), ``sb.actuators``, ``sb.obstacles`` (``sb.obstacles.Plane``,
...), ``sb.contact`` (the contact solver), ``sb.skeleton``, ``sb.control``, ``sb.linsolve``,
``sb.io``.

**Float64.** Importing ``softbody`` turns on JAX's 64-bit mode (``jax_enable_x64``; at once if
JAX is imported, otherwise as JAX is imported: ``import softbody`` itself stays quick): the
simulator's tolerances and the finite-difference gradient checks assume float64, and arrays
you pass in float32 are promoted. To keep JAX's default 32-bit mode, set the environment
variable ``SOFTBODY_FLOAT64=0`` before importing (then softbody leaves ``jax_enable_x64``
as it finds it).

The distribution installs one namespace: ``softbody`` (the simulator),
``softbody.meshing`` (the repository's ``meshing/`` folder), ``softbody.actuators``
(``actuators/``) and ``softbody.control`` (``control/``).

Importing ``softbody`` also turns on JAX's persistent compilation cache in
``$SOFTBODY_CACHE_DIR/xla`` (default ``~/.cache/softbody/xla``), so later runs load the
programs they compiled before; ``SOFTBODY_COMPILATION_CACHE=0`` turns it off, and your own
``JAX_COMPILATION_CACHE_DIR`` wins (see :mod:`softbody.cache`).
"""

import importlib
import importlib.abc
import importlib.util
import os
import sys


def _configure_jax() -> None:
    """Float64 (unless ``SOFTBODY_FLOAT64=0``) and the compilation cache; runs once JAX is imported."""
    import jax

    from softbody import cache

    if os.environ.get("SOFTBODY_FLOAT64", "1").strip().lower() not in ("0", "false", "no", "off"):
        jax.config.update("jax_enable_x64", True)
    cache.setup()


class _WhenJaxIsImported(importlib.abc.MetaPathFinder):
    """Runs :func:`_configure_jax` right after the first ``import jax`` of the process.

    ``import softbody`` does not import JAX itself (1.5-9 s: the command line speaks before
    it), yet no JAX array can be made before float64 and the cache are set up.
    """

    def find_spec(self, name, path=None, target=None):
        if name != "jax":
            return None
        sys.meta_path.remove(self)
        spec = importlib.util.find_spec(name)
        if spec is None or spec.loader is None:
            return spec
        load = spec.loader.exec_module

        def load_and_configure(module):
            load(module)
            _configure_jax()

        spec.loader.exec_module = load_and_configure
        return spec


if "jax" in sys.modules:
    _configure_jax()
elif not any(isinstance(finder, _WhenJaxIsImported) for finder in sys.meta_path):
    sys.meta_path.insert(0, _WhenJaxIsImported())

__version__ = "0.1.0"

#: The flat namespace: public name -> the module that defines it.
_NAMES = {
    **dict.fromkeys(("Model", "Options", "Params", "Prepared", "SceneError", "State", "StepInfo"), "softbody._types"),
    **dict.fromkeys(("build", "initial_state", "prepare"), "softbody.model"),
    **dict.fromkeys(("Fix", "SoftBody"), "softbody.scene"),
    "Material": "softbody.material",
    "RigidBody": "softbody.rigid",
    **dict.fromkeys(("Bending", "Membrane", "shell_body"), "softbody.shell"),
    "Drag": "softbody.aero",
    "Skeleton": "softbody.skeleton",
    "Contact": "softbody.contact",
    "Touch": "softbody.contact.pairs",
    "RESULTS": "softbody._types",
    **dict.fromkeys(("BDF2", "ImplicitEuler", "SimulationError", "Trajectory", "check_trajectory", "contact_fields",
                    "contact_forces", "rollout", "solve_static", "step"), "softbody.simulate"),
    **dict.fromkeys(("LBFGS", "LocalGlobal"), "softbody.solvers"),
    **dict.fromkeys(("Adjoint", "Implicit", "ImplicitForward", "Unrolled", "check_grad"), "softbody.gradients"),
}
#: Submodules reachable as attributes (``sb.meshing``, ``sb.contact``, ...): name -> module.
_MODULES = {**{name: f"softbody.{name}" for name in ("actuators", "contact", "control", "io", "linsolve", "meshing",
                                                     "reference", "render", "skeleton", "viewer")},
            "obstacles": "softbody.contact.obstacles", "pairs": "softbody.contact.pairs"}

__all__ = sorted(_NAMES) + list(_MODULES)


def __getattr__(name: str):
    if name in _NAMES:
        value = getattr(importlib.import_module(_NAMES[name]), name)
    elif name in _MODULES:
        value = importlib.import_module(_MODULES[name])
    else:
        raise AttributeError(f"module 'softbody' has no attribute {name!r}")
    globals()[name] = value
    return value


def __dir__():
    return sorted(set(globals()) | set(__all__))
