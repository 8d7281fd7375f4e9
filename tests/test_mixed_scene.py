"""A scene of two soft bodies (a worm with a muscle, a stiffer pad) and two rigid bodies (a
brick and a faceted can) sliding down one friction plane: every step of 2 s converges and
each body slides as Coulomb friction says; the gradients with respect to the initial
velocity, friction and the worm's Young's modulus match central differences."""

import equinox as eqx
import jax.numpy as jnp
import numpy as np
import pytest

from softbody.actuators import Muscle
from softbody.contact import Contact
from softbody.gradients import check_grad
from softbody.material import Material
from softbody.meshing.grid import grid_box
from softbody.model import Options, build, initial_state
from softbody.contact.obstacles import Plane
from softbody.rigid import RigidBody
from softbody.scene import SoftBody
from softbody.simulate import rollout

from incline import G, rot_y
from test_rigid import box, cylinder

TAN, MU, DT = 0.7, 0.4, 0.01
R = rot_y(np.arctan(TAN))


def _scene(options):
    """The four bodies on the plane tilted by ``arctan(TAN)`` about y, their start on it and
    the worm's muscle controls (0.5 + 0.5 sin(4 pi t))."""
    worm = grid_box((0.08, 0.02, 0.02), (4, 1, 1))
    muscle = Muscle.from_polyline(worm, [[0.0, 0.01, 0.018], [0.08, 0.01, 0.018]], radius=0.01,
                                  stiffness=2e4, falloff="none", name="m")
    bodies = [SoftBody(worm, Material(E=5e4, nu=0.3, density=1000.0), actuators=[muscle], name="worm"),
              SoftBody(grid_box((0.04, 0.04, 0.02), (2, 2, 1), origin=(0.0, 0.1, 0.0)),
                       Material(E=2e5, nu=0.45, density=1200.0), name="pad"),
              RigidBody(box((0.05, 0.03, 0.02)), density=700.0, name="brick", x0=(0.02, -0.1, 0.01)),
              RigidBody(cylinder(0.02, 0.03, 12), density=900.0, name="can", x0=(0.02, 0.2, 0.015))]
    model, params = build(bodies, obstacles=[Plane(normal=tuple(R[:, 2]), mu_s=MU, mu_k=MU)], options=options)
    x0 = jnp.asarray(np.asarray(model.mesh.points) @ R.T)
    controls = jnp.asarray(0.5 + 0.5 * np.sin(4 * np.pi * DT * np.arange(200)))[:, None]
    return model, params, x0, controls


@pytest.mark.slow
def test_two_soft_and_two_rigid_bodies_slide_for_two_seconds():
    """200 steps, every one converged (measured: iterations median 55.5, max 154); no vertex
    ends more than 1 um below the plane; the rigid bodies' centres travel implicit Euler's
    ``a h^2 N (N + 1) / 2`` with ``a = g (sin - mu cos)`` within 1e-9 (measured 2e-14: each
    is a rigid motion under forces proportional to its mass), the pad's within 1e-4
    (measured 2.4e-6: it deforms as it sets down) and the worm's within 2% (measured 1.1%
    farther: its muscle pulls it along)."""
    model, params, x0, controls = _scene(Options(dt=DT, tol=1e-8, max_iter=2000))
    traj = rollout(model, params, initial_state(model, params, x=x0), n_steps=200, controls=controls)
    assert bool(np.all(traj.info.converged))
    x = np.asarray(traj.x)
    assert (x @ R[:, 2]).min() > -1e-6
    theta = np.arctan(TAN)
    a = G * (np.sin(theta) - MU * np.cos(theta))
    expected = a * DT**2 * 200 * 201 / 2
    for part in model.bodies:
        s, e = part.vertices
        travel = float(((x[-1, s:e] - x[0, s:e]) @ R[:, 0]).mean())
        tol = {"brick": 1e-9, "can": 1e-9, "pad": 1e-4, "worm": 0.02}[part.name]
        assert abs(travel / expected - 1) < tol, f"{part.name}: {travel:.4f} m against {expected:.4f} m"



@pytest.mark.slow
def test_gradients_of_the_mixed_scene_match_central_differences():
    """Over 5 steps (tol 1e-12) the gradients of a random weighting of the final positions
    with respect to the initial velocity, the friction coefficient and the worm's Young's
    modulus match central differences within 1e-6. The differences' error is their
    truncation (Richardson: eps^4) plus the forward solves' noise over eps. That noise is
    the tolerance's: the loss (about 1) scatters by 1.5e-12 (standard deviation over 25
    moduli 2e-5 apart in log E; 7e-15 with ``Contact(rigid_floor=0)``, whose iteration
    overshoots the tolerance here), so eps = 1e-4 left the friction and modulus checks at
    1.2e-7 and 8.5e-7, and eps = 1e-3 is used (measured: velocity 4.5e-9, friction 9.9e-8,
    modulus 1.6e-7). The worm's modulus moves the loss 200 times less than the velocity
    (d/dlog E = -2.6e-3), so it enters as ``E = E0 exp(30 s)``, a step in ``s`` as telling
    as one in the others; tol = 1e-13 is out of reach (the gradient is not finite). The
    brick's mass changes nothing (every force on a free rigid body on a plane scales with
    its mass): its gradient vanishes, below 1e-9 of the others."""
    model, params, x0, controls = _scene(
        Options(dt=DT, tol=1e-12, atol=0.0, max_iter=5000, contact=Contact(adjoint_tol=1e-13)))
    weights = jnp.asarray(np.random.default_rng(0).standard_normal((model.n_vertices, 3)))
    worm = list(model.material_names).index("worm/default")

    def loss(theta):
        p = eqx.tree_at(lambda q: q.obstacles[0], params,
                        params.obstacles[0].replace(mu_s=theta["mu"], mu_k=theta["mu"]))
        p = p.replace(rigid_mass=p.rigid_mass.at[0].set(theta["mass"]),
                      E=p.E.at[worm].set(params.E[worm] * jnp.exp(30.0 * theta["s"])))
        start = initial_state(model, p, x=x0, v=jnp.broadcast_to(theta["v"], (model.n_vertices, 3)))
        return jnp.sum(weights * rollout(model, p, start, n_steps=5, controls=controls[:5]).x[-1])

    theta = {"mass": params.rigid_mass[0], "v": jnp.array([0.2, 0.05, 0.0]), "mu": jnp.asarray(MU),
             "s": jnp.asarray(0.0)}
    result = check_grad(loss, theta, directions={k: {j: j == k for j in theta} for k in theta}, eps=1e-3)
    smooth = ("v", "mu", "s")
    for name in smooth:
        assert result[name]["rel_error"] < 1e-6, (name, result[name])
    assert abs(result["mass"]["ad"]) < 1e-9 * min(abs(result[k]["ad"]) for k in smooth)
