"""The contact solver's fast iteration (softbody.contact.active_set): the splitting's fixed point,
reached in fewer iterations, with the same implicit derivative, and the fallback to the
splitting when a touching vertex is not among its candidates.

Scenes are small structured grid boxes (27 vertices) on obstacles, one step each, solved
to a tight tolerance so that two solvers' answers can be compared far below the size of
the motion.
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from softbody.contact.active_set import ActiveSet
from softbody.contact import Contact
from softbody.material import Material
from softbody.meshing.grid import grid_box
from softbody.meshing import Region
from softbody.model import Options, SceneError, build, initial_state, prepare
from softbody.scene import SoftBody
from softbody.contact.obstacles import Plane, Sphere
from softbody.simulate import step
from softbody.skeleton import Free, Link, Skeleton
from softbody.solvers import LocalGlobal

from incline import rot_y

EDGE = 0.1
DT = 1 / 30
TOL = 1e-8


def _solve(obstacles, contact, young=1e6, x=None, cells=2):
    """One step of a box of ``cells^3`` hexahedra (6 tets each) from rest:
    ``(positions, info, jvp in E, start)``."""
    mesh = grid_box((EDGE,) * 3, (cells,) * 3, origin=(-EDGE / 2, -EDGE / 2, 0.0))
    opts = Options(dt=DT, tol=TOL, max_iter=3000, solver=LocalGlobal(), contact=contact)
    model, params = build(SoftBody(mesh, Material(E=young, nu=0.3)), options=opts, obstacles=obstacles)
    x0 = jnp.asarray(mesh.points if x is None else x(mesh.points))
    state0 = initial_state(model, params, x=x0)

    def run(e):
        state, info = step(model, prepare(model, params.replace(E=jnp.full_like(params.E, e))), state0)
        return state.x, info

    (x, info), (dx, _) = jax.jit(lambda e: jax.jvp(run, (e,), (jnp.ones_like(e),)))(jnp.asarray(young))
    return np.asarray(x), info, np.asarray(dx), np.asarray(x0)


def _tilted(theta, mu=0.5):
    """The box set on a plane tilted by ``theta`` about y (``x`` maps rest positions).

    Static and kinetic friction are equal: with ``mu_s > mu_k`` a vertex whose slip lies in
    the band between them has two equilibria, and two solvers may well find different ones.
    """
    r = rot_y(theta)
    return [Plane(normal=r[:, 2], mu_s=mu, mu_k=mu)], lambda p: p @ r.T


SCENES = {
    # sliding: tan(0.6) = 0.68 > mu, every bottom vertex slides
    "sliding on a tilted plane": _tilted(0.6),
    # sticking on a tilted plane, stiff: the diagonal splitting needs hundreds of iterations
    "sticking, stiff": _tilted(0.2) + (1e7,),
    # a curved obstacle: every contact has its own normal, so the active set mixes them
    "on a sphere": ([Sphere(center=(0.0, 0.0, -1.0), radius=1.0, mu_s=0.2, mu_k=0.2)], None, 1e5),
}


@pytest.mark.parametrize("name", list(SCENES))
def test_fast_iteration_reaches_the_splittings_fixed_point(name):
    obstacles, x, *young = SCENES[name]
    young = young[0] if young else 1e6
    cells = 3 if young >= 1e7 else 2
    fast = _solve(obstacles, Contact(active_set=ActiveSet()), young, x, cells)
    plain = _solve(obstacles, Contact(), young, x, cells)
    (x_fast, info_fast, dx_fast, _), (x_plain, info_plain, dx_plain, start) = fast, plain
    assert bool(info_fast.converged) and bool(info_plain.converged)
    assert not bool(info_fast.fallback)
    # the same fixed point: both at a force residual of 1e-10 of |M s / h^2|
    motion = np.abs(x_plain - start).max()
    assert motion > 1e-6
    assert np.abs(x_fast - x_plain).max() <= 1e-6 * motion, name
    # the same implicit derivative, through the fast map and through the splitting map
    scale = np.abs(dx_plain).max()
    assert scale > 0
    np.testing.assert_allclose(dx_fast, dx_plain, rtol=0, atol=1e-4 * scale, err_msg=name)
    # in fewer iterations (the check by the splitting map included); far fewer where the
    # splitting's contraction is slowest, on the stiff body
    fewer = 2 if young >= 1e7 else 1
    assert int(info_fast.iterations) * fewer < int(info_plain.iterations), (info_fast.iterations,
                                                                            info_plain.iterations)


def test_a_touching_vertex_outside_the_candidates_falls_back_to_the_splitting():
    obstacles, x = _tilted(0.6)
    # 9 bottom vertices touch; 4 candidates cannot hold the box
    x_few, info, _, _ = _solve(obstacles, Contact(active_set=ActiveSet(max_contacts=4)), 1e6, x)
    x_plain, _, _, _ = _solve(obstacles, Contact(), 1e6, x)
    assert bool(info.converged) and bool(info.fallback)
    np.testing.assert_allclose(x_few, x_plain, atol=1e-9)
    normal = rot_y(0.6)[:, 2]
    assert (x_few @ normal).min() >= -1e-12  # on or above the plane


def test_a_scene_with_a_skeleton_refuses_it(no_compiling):
    mesh = grid_box((EDGE,) * 3, (2, 2, 2))
    mesh = mesh.with_regions(**{"bone:body": Region(np.arange(mesh.n_vertices), np.arange(mesh.n_tets))})
    skeleton = Skeleton([Link("body", "bone:body", None, Free())])
    with pytest.raises(SceneError, match="active_set=None"):
        build(SoftBody(mesh, Material()),
              skeleton=skeleton, obstacles=[Plane()], options=Options(contact=Contact(active_set=ActiveSet())))


def test_bad_settings_are_refused():
    for bad in ({"max_contacts": 0}, {"history": -1}, {"max_iter": 1.5}):
        with pytest.raises(ValueError, match="ActiveSet"):
            ActiveSet(**bad)
    with pytest.raises(ValueError, match="active_set"):
        Contact(active_set="fast")
