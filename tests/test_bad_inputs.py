"""Bad inputs a new user hits: each is refused with a message that names the problem and
the fix, before anything compiles where the input allows (a viewer port out of range, a
material value out of range or not a number, a fractional step count, a state of another
model), and the command line speaks of its own options."""

import argparse
import errno
import socket
import subprocess
import sys
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from test_io import box_result

from softbody import demo, viewer
from softbody._types import Params
from softbody.cli import main
from softbody.material import Material
from softbody.meshing import save
from softbody.meshing.grid import grid_box
from softbody.actuators import Muscle
from softbody.model import Options, SceneError, build, initial_state, prepare
from softbody.scene import SoftBody
from softbody.simulate import rollout, solve_static, step

ROOT = Path(__file__).resolve().parents[1]
#: A 0.1 x 0.02 x 0.02 m beam on 5 x 1 x 1 cells (24 vertices, 30 tets), clamped at x = 0.
BEAM = grid_box((0.1, 0.02, 0.02), (5, 1, 1))


@pytest.fixture(scope="module")
def beam():
    """The beam built (nothing compiled: every check here comes first)."""
    return build(SoftBody(BEAM, Material(E=1e5, nu=0.3), fixed="fixed"))


@pytest.fixture(scope="module")
def result_file(tmp_path_factory):
    path = tmp_path_factory.mktemp("view") / "result.npz"
    box_result(frames=2, with_extras=False).save(path)
    return path


@pytest.fixture
def no_server(monkeypatch):
    """Make starting a viser server fail the test: a bad port or host must be refused first."""
    def server(*args, **kwargs):
        raise AssertionError("the viewer started a server for a port or host it should have refused")

    monkeypatch.setattr(viewer.viser, "ViserServer", server)


# --------------------------------------------------------------------------------------
# The viewer's port and host
# --------------------------------------------------------------------------------------


@pytest.mark.parametrize("port", ["99999", "-5"])
def test_view_command_refuses_a_port_out_of_range_at_once(port, result_file):
    """It used to print a server thread's traceback and then wait forever."""
    argv = [sys.executable, "-m", "softbody.cli", "view", str(result_file), "--port", port]
    proc = subprocess.run(argv, capture_output=True, text=True, timeout=60, stdin=subprocess.DEVNULL, check=False)
    assert proc.returncode == 2, proc.stderr
    assert f"argument --port: '{port}' is not a TCP port: give an integer from 0 to 65535" in proc.stderr
    assert "Traceback" not in proc.stderr


@pytest.mark.parametrize("port", [99999, -5, 80.5, "8080"])
def test_view_refuses_a_port_out_of_range(port, no_server):
    with pytest.raises(ValueError, match=r"is not a TCP port: give an integer from 0 to 65535 \(0: any free port\)"):
        viewer.view(box_result(frames=2, with_extras=False), port=port, block=False)


def test_view_command_refuses_an_address_of_another_machine(result_file, no_server, capsys):
    """192.0.2.1 (a documentation address) is no interface of this machine."""
    assert main(["view", str(result_file), "--host", "192.0.2.1", "--port", "0"]) == 1
    err = capsys.readouterr().err
    assert err.startswith("softbody view: cannot serve on 192.0.2.1:0:") and "use host 127.0.0.1" in err


def test_a_taken_port_is_reported_with_the_one_used(capsys):
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen(1)
        port = taken.getsockname()[1]
        with viewer.view(box_result(frames=2, with_extras=False), port=port, block=False) as shown:
            assert shown.port != port and shown.url.endswith(f":{shown.port}")
    assert f"softbody viewer: port {port} is in use; serving on port {shown.port}" in capsys.readouterr().err


def test_the_last_port_taken_is_refused_not_overflowed():
    with socket.socket() as taken:
        try:
            taken.bind(("127.0.0.1", 65535))
            taken.listen(1)
        except OSError as err:
            if err.errno != errno.EADDRINUSE:
                raise
        with pytest.raises(ValueError, match="ports 65535 to 65535 on 127.0.0.1 are all in use; pass port 0"):
            viewer.free_port("127.0.0.1", 65535)


# --------------------------------------------------------------------------------------
# Material values: Material and Params.replace share the rules
# --------------------------------------------------------------------------------------


@pytest.mark.parametrize("kwargs, message", [
    ({"E": "1e5"}, r"Material.E = '1e5' is not a number \(write the number without quotes\): Young's modulus"),
    ({"nu": None}, "Material.nu = None is not a number: Poisson's ratio"),
    ({"density": True}, "Material.density = True is not a number"),
    ({"alpha": [1.0]}, r"Material.alpha = \[1.0\] is not a single number"),
])
def test_material_refuses_what_is_not_a_number(kwargs, message):
    with pytest.raises(TypeError, match=message):
        Material(**kwargs)


@pytest.mark.parametrize("change, error, message", [
    ({"E": [-1e5]}, ValueError, r"Params.E = \[-100000.0\]: Young's modulus must be a positive number"),
    ({"E": jnp.array([-1e5])}, ValueError, r"Params.E = \[-100000.0\]: Young's modulus"),
    ({"E": -1e5}, ValueError, "Params.E = -100000.0: Young's modulus"),
    ({"nu": [0.6]}, ValueError, r"Params.nu = \[0.6\]: Poisson's ratio must lie in \(-1, 0.5\)"),
    ({"nu": np.array([np.nan])}, ValueError, "Params.nu = \\[nan\\]: Poisson's ratio"),
    ({"density": [0.0]}, ValueError, "density must be positive"),
    ({"beta": [-1.0]}, ValueError, "stiffness damping beta must be >= 0"),
    ({"E": "1e5"}, TypeError, "Params.E = '1e5' is not a number"),
    ({"E": [1e5, 2e5]}, SceneError, r"Params.E has shape \(2,\) but must have shape \(1,\): one value per material"),
])
def test_params_replace_checks_material_values_before_compiling(beam, change, error, message):
    _, params = beam
    with pytest.raises(error, match=message):
        params.replace(**change)


def test_params_replace_takes_a_number_for_the_one_material(beam):
    _, params = beam
    stiffer = params.replace(E=2e5, nu=0.4)
    assert stiffer.E.shape == (1,) and stiffer.E.dtype == params.E.dtype
    np.testing.assert_array_equal(stiffer.E, [2e5])
    np.testing.assert_array_equal(stiffer.nu, [0.4])


def test_params_replace_refuses_a_number_for_several_materials():
    two = Params(E=jnp.full(2, 1e5), nu=jnp.full(2, 0.3), density=jnp.full(2, 1e3), alpha=jnp.zeros(2),
                 beta=jnp.zeros(2), morph=jnp.zeros((4, 3)), rigid_mass=jnp.zeros(0))
    with pytest.raises(SceneError, match=r"shape \(\) but must have shape \(2,\).*jnp.full\(2, value\)"):
        two.replace(E=2e5)


def test_params_replace_leaves_traced_values_alone(beam):
    """Inside jit or grad the value is unknown: no check, no forced concretisation."""
    _, params = beam
    np.testing.assert_array_equal(jax.jit(lambda e: params.replace(E=e).E)(jnp.array([-1.0])), [-1.0])
    np.testing.assert_array_equal(jax.grad(lambda e: params.replace(E=2 * e).E.sum())(params.E), [2.0])


# --------------------------------------------------------------------------------------
# rollout's inputs
# --------------------------------------------------------------------------------------


@pytest.mark.parametrize("n_steps", [2.5, 2.0, "3", True])
def test_rollout_refuses_a_step_count_that_is_not_a_whole_number(beam, n_steps):
    model, params = beam
    with pytest.raises(SceneError, match=f"n_steps must be a whole number of steps, got {n_steps!r}"):
        rollout(model, params, initial_state(model, params), n_steps=n_steps)


def test_rollout_refuses_a_state_or_params_of_another_model(beam):
    model, params = beam
    other, other_params = build(SoftBody(grid_box((0.1, 0.02, 0.02), (2, 1, 1)), Material(), fixed="fixed"))
    state = initial_state(model, params)
    with pytest.raises(SceneError, match=r"state0.x has shape \(12, 3\) but this model \(24 vertices, 30 tets, "
                                         r"1 material\(s\)\) needs \(24, 3\): it belongs to another model"):
        rollout(model, params, initial_state(other, other_params), n_steps=2)
    with pytest.raises(SceneError, match=r"params.morph has shape \(12, 3\) .* needs \(24, 3\)"):
        rollout(model, other_params, state, n_steps=2)


def test_every_rollout_refuses_a_fractional_step_count_or_a_state_of_another_model(beam, no_compiling, monkeypatch):
    """policy_rollout ran int(2.5) = 2 steps; explicit_rollout and newton_rollout took a state
    or params of another model as far as JAX's broadcasting error."""
    import softbody.control as sc
    import softbody.control.policy

    from softbody.explicit import explicit_rollout
    from softbody.reference import newton_rollout

    monkeypatch.setattr(softbody.control.policy, "_policy_rollout", lambda *a, **k: pytest.fail("policy_rollout compiled"))
    model, params = beam
    other, other_params = build(SoftBody(grid_box((0.1, 0.02, 0.02), (2, 1, 1)), Material(), fixed="fixed"))
    state, alien = initial_state(model, params), initial_state(other, other_params)
    obs = sc.Observations(model, [None], periods=[0.1])
    def policy(observation):  # the beam has no actuators: zero channels
        return jnp.zeros(model.n_channels)
    with pytest.raises(sc.ControlError, match="n_steps must be a whole number of steps, got 2.5"):
        sc.policy_rollout(model, params, policy, obs, 2.5)
    with pytest.raises(SceneError, match=r"state0.x has shape \(12, 3\) but this model .* needs \(24, 3\)"):
        sc.policy_rollout(model, params, policy, obs, 2, alien)
    for run in (explicit_rollout, newton_rollout):
        with pytest.raises(SceneError, match="n_steps must be a whole number of steps, got 2.5"):
            run(model, params, state, n_steps=2.5)
        with pytest.raises(SceneError, match=r"state0.x has shape \(12, 3\) but this model .* needs \(24, 3\)"):
            run(model, params, alien, n_steps=2)
        with pytest.raises(SceneError, match=r"params.morph has shape \(12, 3\) .* needs \(24, 3\)"):
            run(model, other_params, state, n_steps=2)


def test_step_refuses_a_state_or_prep_of_another_model(beam, no_compiling):
    """step and solve_static used to fail inside JAX with "add got incompatible shapes"."""
    model, params = beam
    other, other_params = build(SoftBody(grid_box((0.1, 0.02, 0.02), (2, 1, 1)), Material(), fixed="fixed"))
    state = initial_state(model, params)
    with pytest.raises(SceneError, match=r"state.x has shape \(12, 3\) but this model .* needs \(24, 3\): it belongs "
                                         r"to another model; use initial_state\(model, params\)"):
        step(model, prepare(model, params), initial_state(other, other_params))
    with pytest.raises(SceneError, match=r"prep.x_rest has shape \(12, 3\) .* use prepare\(model, params\)"):
        step(model, prepare(other, other_params), state)
    with pytest.raises(SceneError, match=r"force must have shape \(24, 3\) .* got \(3, 3\)"):
        step(model, prepare(model, params), state, force=jnp.zeros((3, 3)))


def test_solve_static_refuses_params_or_a_force_of_another_model(beam, no_compiling):
    model, params = beam
    other, other_params = build(SoftBody(grid_box((0.1, 0.02, 0.02), (2, 1, 1)), Material(), fixed="fixed"))
    with pytest.raises(SceneError, match=r"params.morph has shape \(12, 3\) .* needs \(24, 3\): it belongs to another "
                                         r"model; use the params build returned with this model"):
        solve_static(model, other_params)
    with pytest.raises(SceneError, match=r"force must have shape \(24, 3\)"):
        solve_static(model, params, force=jnp.zeros((12, 3)))


def test_activations_out_of_bounds_are_refused_when_concrete_and_clipped_when_traced():
    """Under jit the value is unknown: no check (it would need a host callback, which keeps a
    program out of the compilation cache); the terms clip it (tests/test_actuators.py) and
    the documentation says so."""
    muscle = Muscle.from_polyline(BEAM, [[0.0, 0.01, 0.01], [0.1, 0.01, 0.01]], radius=0.02)
    model, params = build(SoftBody(BEAM, Material(E=1e5, nu=0.3), fixed="fixed", actuators=(muscle,)),
                          options=Options(gravity=(0.0, 0.0, 0.0)))
    state = initial_state(model, params)
    with pytest.raises(SceneError, match=r"controls\[0, 0\] \(step 0\) = 1.5 is outside channel .* \[0, 1\]"):
        rollout(model, params, state, controls=jnp.full((1, 1), 1.5))
    traced = jax.make_jaxpr(lambda c: rollout(model, params, state, controls=c, throw=False))(jnp.full((1, 1), 1.5))
    assert "callback" not in str(traced)
    assert "clipped to the bounds without an error or a flag" in " ".join(rollout.__doc__.split())
    sharp_bits = " ".join((ROOT / "docs" / "sharp-bits.md").read_text().split())
    assert "under `jax.jit`/`jax.grad`/`jax.vmap` their values are unknown: there they are clipped" in sharp_bits


# --------------------------------------------------------------------------------------
# The command line
# --------------------------------------------------------------------------------------


def test_run_command_gives_advice_in_its_own_options(tmp_path, capsys):
    mesh = save(BEAM, tmp_path / "beam.msh")
    out = tmp_path / "r.npz"
    assert main(["run", str(mesh), "--steps", "1", "--gravity", "0", "0", "-1e6", "-o", str(out)]) == 1
    err = capsys.readouterr().err
    assert err.startswith("softbody run: step 0: tets inverted (det F <= 0)")
    assert "lower --gravity, raise --E (now 100000 Pa)" in err and "reduce --dt (now 0.01 s)" in err
    assert "throw=False" not in err and "rollout(" not in err and "activations" not in err
    assert not out.exists()


def test_git_ignores_the_demo_default_output_folder():
    """`bash scripts/setup.sh demo` runs `softbody demo` in the repository's root."""
    parser = argparse.ArgumentParser()
    demo.add_arguments(parser)
    folder = parser.parse_args([]).out
    ignored = (ROOT / ".gitignore").read_text().splitlines()
    assert f"{folder}/" in ignored or f"/{folder}/" in ignored, f"{folder}/ is not in .gitignore"
