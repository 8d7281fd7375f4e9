"""Scene data types: build resolves defaults once, models compare by content, Params
replace and check their fields."""

import dataclasses

import jax.numpy as jnp
import numpy as np
import pytest

from softbody.contact import Contact
from softbody.gradients import Implicit, Unrolled
from softbody.linsolve import DenseCholesky
from softbody.material import Material
from softbody.meshing.grid import grid_box
from softbody.model import Options, SceneError, build, initial_state
from softbody.scene import SoftBody
from softbody.contact.obstacles import Plane
from softbody.simulate import _rollout, rollout
from softbody.solvers import LBFGS, LocalGlobal, Step, Vertices
from softbody.contact.splitting import Diagonal

MESH = grid_box((0.04, 0.01, 0.01), (4, 1, 1))


def _build(**kwargs):
    return build(SoftBody(MESH, Material(E=1e5, nu=0.3), fixed="xmin"), **kwargs)


def test_build_resolves_defaults_once():
    model, _ = _build()
    assert model.step == Step(Vertices(), LBFGS(), None) and model.options.solver is model.step.solver
    assert isinstance(model.options.adjoint, Implicit) and model.options.contact is None and model.rig is None
    assert model.options.linear_solver is not None and model.linear_solver is model.options.linear_solver
    contact, _ = build(SoftBody(MESH, Material()), obstacles=[Plane()])
    # the contact adjoint's tolerance follows the forward one (Options.tol = 1e-4 -> 1e-5)
    assert contact.step == Step(Vertices(), LBFGS(), Contact(adjoint_tol=1e-5))
    assert contact.options.contact is contact.step.contact
    tight, _ = build(SoftBody(MESH, Material()), obstacles=[Plane()], options=Options(tol=1e-12))
    assert tight.step.contact.adjoint_tol == 1e-10
    chosen = Options(solver=LocalGlobal(), adjoint=Unrolled(), linear_solver=DenseCholesky())
    model, _ = _build(options=chosen)
    assert model.options == chosen  # what the user chose is kept as given
    assert model.step == Step(Vertices(), LocalGlobal(), None)
    mine = Contact(splitting=Diagonal(), history=5, adjoint_tol=1e-7)
    model, _ = build(SoftBody(MESH, Material()), obstacles=[Plane()], options=Options(contact=mine))
    assert model.step.contact is mine and model.options.contact is mine


def test_unsupported_combinations_are_refused_before_compiling(no_compiling):
    """Each refusal names what is supported (build composes the step before compiling)."""
    with pytest.raises(SceneError, match="Options.contact sets the contact solver, but the scene has no obstacles"):
        _build(options=Options(contact=Contact()))
    with pytest.raises(SceneError, match="a step with contact is differentiated through the fixed point"):
        build(SoftBody(MESH, Material()), obstacles=[Plane()], options=Options(adjoint=Unrolled()))
    with pytest.raises(SceneError, match="Options.solver must be a nonlinear solver"):
        _build(options=Options(solver=Contact()))
    with pytest.raises(SceneError, match="Options.contact must be a softbody.contact.Contact"):
        build(SoftBody(MESH, Material()), obstacles=[Plane()], options=Options(contact=LBFGS()))
    with pytest.raises(SceneError, match="Options.adjoint must be"):
        _build(options=Options(adjoint="implicit"))


def test_models_compare_by_content_and_share_compiled_code():
    a, params = _build()
    b, _ = _build()
    assert a is not b and a == b and hash(a) == hash(b)
    assert a != _build(options=Options(dt=0.02))[0]
    assert a == build(SoftBody(MESH, Material(E=2e5, nu=0.3), fixed="xmin"))[0]  # E is a Param: no recompile
    other = dataclasses.replace(MESH, points=MESH.points * 1.01)
    assert a != build(SoftBody(other, Material(E=1e5, nu=0.3), fixed="xmin"))[0]
    assert a != build(SoftBody(MESH, Material(E=1e5, nu=0.3), fixed="xmax"))[0]
    rollout(a, params, initial_state(a, params), n_steps=2)
    size = _rollout._cache_size()
    rollout(b, params, initial_state(b, params), n_steps=2)
    assert _rollout._cache_size() == size  # the rebuilt scene reused the compiled rollout


def test_params_replace():
    _, params = _build()
    doubled = params.replace(E=params.E * 2)
    np.testing.assert_array_equal(doubled.E, params.E * 2)
    np.testing.assert_array_equal(doubled.nu, params.nu)
    with pytest.raises(SceneError, match=r"no field\(s\) \['young'\]; its fields are"):
        params.replace(young=1.0)
    with pytest.raises(SceneError, match="Params.nu has shape"):
        params.replace(nu=jnp.ones(3))
    with pytest.raises(SceneError, match=r"Params.morph must be \(n, 3\)"):
        params.replace(morph=jnp.zeros(5))


def test_float64_switch_and_its_opt_out():
    """Importing softbody turns on float64; SOFTBODY_FLOAT64=0 set before importing keeps
    JAX's 32-bit default (the documented opt-out)."""
    import os
    import subprocess
    import sys

    code = "import softbody as sb, jax.numpy as jnp; print(jnp.zeros(1).dtype, sb.Options.__name__)"
    env = {k: v for k, v in os.environ.items() if k not in ("JAX_ENABLE_X64", "SOFTBODY_FLOAT64")}
    on = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, timeout=120)
    off = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120,
                         env={**env, "SOFTBODY_FLOAT64": "0"})
    assert on.stdout.split() == ["float64", "Options"], on.stderr
    assert off.stdout.split() == ["float32", "Options"], off.stderr


def test_flat_namespace():
    import softbody as sb

    assert sb.build is build and sb.Options is Options and sb.rollout is rollout
    assert sb.obstacles.Plane is Plane and sb.meshing.grid.grid_box is grid_box
    missing = [name for name in sb.__all__ if not hasattr(sb, name)]
    assert not missing, missing
    with pytest.raises(AttributeError, match="no attribute 'bulid'"):
        sb.bulid


def test_forward_mode_through_implicit_names_the_fix():
    """jax.jacfwd through the reverse-mode Implicit adjoint is refused at trace time with a
    message naming ImplicitForward (JAX's own message names neither)."""
    import jax

    model, params = _build()

    def tip(E):
        p = params.replace(E=E)
        return rollout(model, p, initial_state(model, p), n_steps=2).x[-1].sum()

    with pytest.raises(TypeError, match=r"Options\(adjoint=softbody.ImplicitForward\(\)\)"):
        jax.jacfwd(tip)(params.E)
