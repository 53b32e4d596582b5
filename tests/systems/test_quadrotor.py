"""QuadrotorSwarm: the validation checks of `shared/reference/quadrotor_spec.md` §7, plus data contracts."""

from __future__ import annotations

from dataclasses import replace

import pytest
import torch

from mpsim.errors import ConfigError, IncompatibleError
from mpsim.systems.quadrotor import QuadrotorSwarm
from mpsim.systems.quadrotor_dynamics import quat_to_rotation
from mpsim.systems.quadrotor_scenarios import CEILING, DOOR_CENTRES, DOOR_RADIUS, LOAD_RADIUS, QUAD_RADIUS, reference

F64 = torch.float64


@pytest.fixture(scope="module")
def quad3() -> QuadrotorSwarm:
    return QuadrotorSwarm(n_quads=3)


@pytest.fixture(scope="module")
def short_run(quad3: QuadrotorSwarm):
    """3 accepted trajectories of the first 3 s (align, circle → fan morph): a few seconds to simulate."""
    return quad3.generate_full(n=3, seed=0, horizon=60)


def _flight(system: QuadrotorSwarm, scenario, seconds: float):
    """Fly `scenario` with the public controller and RK4 step; return final x, load, energy change, rotor work."""
    x, load = scenario.x0.clone(), scenario.load0.clone()
    e0 = system.plant.mechanical_energy(x, load)
    work = torch.zeros(len(scenario), dtype=F64)
    h = system.control_dt / system.substeps
    for k in range(round(seconds / system.control_dt)):
        u, _ = system.controller.control(x, load, scenario, k * system.control_dt)
        for _ in range(system.substeps):
            x, load, _, w = system.plant.step(x, load, u, h)
            work = work + w
    return x, load, system.plant.mechanical_energy(x, load) - e0, work


# ---- physics at a single state ------------------------------------------------------------------------------
@pytest.mark.parametrize("n_quads", [3, 6])
def test_static_trim_hovers(n_quads: int) -> None:
    """§7.1: at trim thrusts in the circle formation nothing accelerates and T_i = m_L g/(N cos α)."""
    system = QuadrotorSwarm(n_quads=n_quads)
    r_config = torch.tensor([1.2, 1.0], dtype=F64)
    x, load, u = system.controller.hover_state(
        torch.tensor([[0.3, -0.2, 0.5], [-1.0, 0.4, 0.3]], dtype=F64),
        r_config,
        torch.tensor([0.3, 1.1], dtype=F64),
    )
    d = system.plant.derivatives(x, load, u)
    assert d.dx[..., 7:].abs().max() < 1e-6  # v̇ and ω̇
    assert d.dload[..., 3:].abs().max() < 1e-6
    cos_alpha = torch.sqrt(1 - (r_config / system.cable_length) ** 2)
    expected = system.load_mass * system.gravity / (n_quads * cos_alpha)
    torch.testing.assert_close(d.tension, expected[:, None].expand(-1, n_quads), rtol=0, atol=1e-9)
    if n_quads == 3:  # the spec's numbers for α = asin(1.2/1.55) ≈ 50.7°
        assert d.tension[0, 0].item() == pytest.approx(4.65, abs=0.01)
        assert u[0, 0, 0].item() == pytest.approx(3.31, abs=0.01)


def test_single_quad_cannot_lift_the_load() -> None:
    """§7.2: one quad at full thrust with the load hanging at rest below it cannot climb (v̇_z = 0 at the bound)."""
    system = QuadrotorSwarm(n_quads=1)
    assert system.rotor_max == pytest.approx(4.66, abs=1e-3)
    x = torch.zeros(1, 1, 13, dtype=F64)
    x[..., 2], x[..., 3] = system.cable_length, 1.0  # straight above the load, level
    load = torch.zeros(1, 6, dtype=F64)
    full = torch.full((1, 1, 4), system.rotor_max, dtype=F64)
    d = system.plant.derivatives(x, load, full)
    assert d.dx[..., 9].item() <= 1e-12 and abs(d.dx[..., 9].item()) < 1e-9
    assert d.dload[..., 5].item() <= 1e-12
    assert d.tension.item() == pytest.approx(system.load_mass * system.gravity, abs=1e-9)
    assert system.plant.derivatives(x, load, 0.99 * full).dx[..., 9].item() < 0
    for _ in range(500):  # 1 s at full thrust: no climb
        x, load, _, _ = system.plant.step(x, load, full, 0.002)
    assert x[..., 2].item() <= system.cable_length + 1e-9


def test_momentum_balance(quad3: QuadrotorSwarm) -> None:
    """§7.4: cable tensions are internal: d/dt(Σ m_q v_i + m_L v_L) = Σ R_i f_i e3 + (N m_q + m_L) g."""
    gen = torch.Generator().manual_seed(5)
    x = torch.randn(4, 3, 13, generator=gen, dtype=F64)
    x[..., 3:7] = x[..., 3:7] / x[..., 3:7].norm(dim=-1, keepdim=True)
    load = torch.randn(4, 6, generator=gen, dtype=F64)
    load[:, 2] -= 3.0  # below the quads
    u = 4 * torch.rand(4, 3, 4, generator=gen, dtype=F64)
    d = quad3.plant.derivatives(x, load, u)
    thrust = (u.sum(-1, keepdim=True) * quat_to_rotation(x[..., 3:7])[..., 2]).sum(1)
    gravity = torch.tensor([0.0, 0.0, -quad3.gravity], dtype=F64) * (3 * quad3.quad_mass + quad3.load_mass)
    lhs = quad3.quad_mass * d.dx[..., 7:10].sum(1) + quad3.load_mass * d.dload[..., 3:]
    torch.testing.assert_close(lhs, thrust + gravity, rtol=0, atol=1e-10)


def test_reference_derivatives_match_finite_differences(quad3: QuadrotorSwarm) -> None:
    """The analytic reference velocity/acceleration (min-jerk blends and morph) are the derivatives of the path."""
    scenario = quad3.sample_scenarios(3, torch.Generator().manual_seed(1))
    eps = 1e-5
    for t in (0.4, 1.7, 2.9, 6.0, 10.3):
        p, v, a, n, _ = reference(scenario, t, quad3.cable_length)
        p_plus, v_plus, *_ = reference(scenario, t + eps, quad3.cable_length)
        p_minus, v_minus, *_ = reference(scenario, t - eps, quad3.cable_length)
        torch.testing.assert_close((p_plus - p_minus) / (2 * eps), v, rtol=0, atol=1e-7)
        torch.testing.assert_close((v_plus - v_minus) / (2 * eps), a, rtol=0, atol=1e-6)
        torch.testing.assert_close(n.norm(dim=-1), torch.ones(3, 3, dtype=F64), rtol=0, atol=1e-14)


def test_energy_balance_short(quad3: QuadrotorSwarm) -> None:
    """§7.3: E(t) − E(0) = ∫ Σ (R f e3·v + τ·ω) dt (rigid cables do no work), over 1.5 s of closed loop."""
    scenario = quad3.sample_scenarios(2, torch.Generator().manual_seed(2))
    _, _, d_energy, work = _flight(quad3, scenario, 1.5)
    assert d_energy.abs().max() > 0.1  # the check is not vacuous
    torch.testing.assert_close(d_energy, work, rtol=0, atol=1e-6)


# ---- generated data ---------------------------------------------------------------------------------
def test_output_shapes_dtype_and_meta(quad3: QuadrotorSwarm, short_run) -> None:
    """§7.12: shapes, float64, no NaN; the graph is complete without self-loops; rejections recorded."""
    traj = short_run.trajectories
    assert traj.x.shape == (3, 61, 3, 13) and traj.u.shape == (3, 61, 3, 4)
    assert short_run.load.shape == (3, 61, 6) and short_run.tension.shape == (3, 61, 3)
    assert traj.x.dtype == traj.u.dtype == short_run.load.dtype == F64
    assert torch.isfinite(traj.x).all() and torch.isfinite(traj.u).all()
    torch.testing.assert_close(traj.t, torch.arange(61, dtype=F64) * 0.05)
    assert traj.edge_index.shape == (2, 6) and (traj.edge_index[0] != traj.edge_index[1]).all()
    assert len(QuadrotorSwarm.state_names) == 13 and len(QuadrotorSwarm.control_names) == 4
    assert traj.meta["state_names"] == list(quad3.state_names) and traj.meta["dt"] == 0.05
    assert traj.meta["seed"] == 0 and traj.meta["n_simulated"] >= 3 and "rejections" in traj.meta
    assert short_run.accepted.all()


def test_cable_length_held(quad3: QuadrotorSwarm, short_run) -> None:
    """§7.5: the Baumgarte-stabilised rigid cables keep |ℓ_i − L| < 1e-4 m."""
    length = (short_run.trajectories.x[..., :3] - short_run.load[:, :, None, :3]).norm(dim=-1)
    assert (length - quad3.cable_length).abs().max() < 1e-4
    assert short_run.checks["max_cable_error"].max() < 1e-4


def test_tensions_positive(short_run) -> None:
    """§7.6: T_i > 0.1 N throughout, at every RK4 step (checks) and at the samples."""
    assert short_run.checks["min_tension"].min() > 0.1
    assert short_run.tension.min() > 0.1


def test_quaternions_unit_without_sign_flips(short_run) -> None:
    """§7.8: |‖q‖ − 1| < 1e-9 after renormalisation and q_w > 0."""
    q = short_run.trajectories.x[..., 3:7]
    assert (q.norm(dim=-1) - 1).abs().max() < 1e-9
    assert q[..., 0].min() > 0 and short_run.checks["min_qw"].min() > 0


def test_inputs_within_bounds(quad3: QuadrotorSwarm, short_run) -> None:
    """§7.9: every u in [0, rotor_max] and no tick saturated on accepted data."""
    u = short_run.trajectories.u
    assert u.min() >= 0 and u.max() <= quad3.rotor_max
    assert (short_run.checks["saturated_ticks"] == 0).all()


def test_geometry_of_the_first_seconds(short_run) -> None:
    """§7.7 (first 3 s): load below every quad, quads apart, inside the room."""
    p = short_run.trajectories.x[..., :3]
    assert (p[..., 2] - short_run.load[:, :, None, 2]).min() > 0.3
    dist = (p[:, :, :, None] - p[:, :, None]).norm(dim=-1) + 10 * torch.eye(3, dtype=F64)
    assert dist.min() > 2 * QUAD_RADIUS
    assert p[..., 2].max() <= CEILING and short_run.load[..., 2].min() >= 0


def test_reproducible_with_seed(quad3: QuadrotorSwarm) -> None:
    a = quad3.generate(n=2, seed=7, horizon=4)
    b = quad3.generate(n=2, seed=7, horizon=4)
    c = quad3.generate(n=2, seed=8, horizon=4)
    assert torch.equal(a.x, b.x) and torch.equal(a.u, b.u)
    assert not torch.equal(a.x, c.x)


def test_one_tick_resimulation(quad3: QuadrotorSwarm) -> None:
    """§7.12: at 100 Hz, integrating one tick from stored x[t], load[t], u[t] gives x[t+1] to 1e-8."""
    run = quad3.generate_full(n=2, seed=3, dt=0.01, horizon=10)
    x, u, load = run.trajectories.x, run.trajectories.u, run.load
    xk, lk = x[:, :-1].flatten(0, 1), load[:, :-1].flatten(0, 1)
    for _ in range(quad3.substeps):
        xk, lk, _, _ = quad3.plant.step(xk, lk, u[:, :-1].flatten(0, 1), quad3.control_dt / quad3.substeps)
    torch.testing.assert_close(xk, x[:, 1:].flatten(0, 1), rtol=0, atol=1e-8)
    torch.testing.assert_close(lk, load[:, 1:].flatten(0, 1), rtol=0, atol=1e-8)


def test_sampled_u_is_the_block_mean_of_the_applied_thrusts(quad3: QuadrotorSwarm) -> None:
    """At dt = 0.05 the recorded u is the mean of the five 100 Hz thrusts it stands for (best zero-order hold)."""
    fine = quad3.generate_full(n=2, seed=4, dt=0.01, horizon=20)
    coarse = quad3.generate_full(n=2, seed=4, dt=0.05, horizon=3)
    torch.testing.assert_close(coarse.trajectories.x, fine.trajectories.x[:, 0:16:5], rtol=0, atol=1e-12)
    blocks = fine.trajectories.u[:, :20].reshape(2, 4, 5, 3, 4).mean(2)
    torch.testing.assert_close(coarse.trajectories.u, blocks, rtol=0, atol=1e-12)


def test_simulate_flies_a_given_scenario(quad3: QuadrotorSwarm) -> None:
    scenario = quad3.sample_scenarios(2, torch.Generator().manual_seed(6))
    traj = quad3.simulate(scenario.x0, torch.arange(4, dtype=F64) * 0.05, scenario=scenario)
    torch.testing.assert_close(traj.x, quad3.rollout(scenario, 0.05, 3).trajectories.x)
    with pytest.raises(ConfigError, match="scenario"):
        quad3.simulate(scenario.x0, torch.arange(4, dtype=F64) * 0.05)


# ---- rejection --------------------------------------------------------------------------------------
def test_door_collision_is_flagged(quad3: QuadrotorSwarm) -> None:
    """A formation started inside the door's cylinders fails the clearance bound."""
    scenario = quad3.sample_scenarios(2, torch.Generator().manual_seed(9))
    shift = torch.tensor([2.75, 0.85], dtype=F64) - scenario.load0[:, :2]  # load onto a cylinder's axis line
    x0, load0 = scenario.x0.clone(), scenario.load0.clone()
    x0[..., :2] += shift[:, None]
    load0[:, :2] += shift
    start = scenario.start.clone()
    start[:, :2] += shift
    run = quad3.rollout(replace(scenario, x0=x0, load0=load0, start=start), 0.05, 1)
    assert quad3.failed_checks(run.checks)["door_collision"].all() and not run.accepted.any()
    centres = torch.tensor(DOOR_CENTRES, dtype=F64)
    clearance = (load0[:, None, :2] - centres).norm(dim=-1).amin(-1) - DOOR_RADIUS - LOAD_RADIUS
    assert (run.checks["min_door_clearance_load"] <= clearance + 1e-12).all()


def test_slack_trajectories_are_resampled() -> None:
    """Trajectories under the tension threshold are rejected and replaced by fresh scenarios."""
    # Trim tension is m_L g/(N cos α): from 3.85 N (r = 1.0 m) to 5.4 N (r = 1.3 m), so a 4.6 N threshold
    # rejects roughly half of the scenarios.
    system = QuadrotorSwarm(n_quads=3, min_tension=4.6, max_rounds=20)
    run = system.generate_full(n=4, seed=0, horizon=2)
    meta = run.trajectories.meta
    assert len(run.trajectories) == 4 and meta["n_rejected"] > 0 and meta["rejections"]["slack_cable"] > 0
    assert run.checks["min_tension"].min() > 4.6
    with pytest.raises(ConfigError, match="rounds"):
        QuadrotorSwarm(n_quads=3, min_tension=100.0, max_rounds=1).generate(n=2, seed=0, horizon=1)


def test_config_errors(quad3: QuadrotorSwarm) -> None:
    with pytest.raises(ConfigError, match="control_dt"):
        quad3.generate(n=1, seed=0, dt=0.025, horizon=2)
    with pytest.raises(ConfigError, match="n_quads"):
        QuadrotorSwarm(n_quads=1).generate(n=1, seed=0, horizon=2)
    with pytest.raises(ConfigError, match="burn_in"):
        quad3.generate(n=1, seed=0, horizon=2, burn_in=3)
    with pytest.raises(ConfigError, match=r"system.quad_mass must be > 0"):  # was a ZeroDivisionError mid-step
        QuadrotorSwarm(quad_mass=0.0)
    with pytest.raises(ConfigError, match=r"system.cable_length, system.inertia\[2\] must be > 0.*got -1.0, nan"):
        QuadrotorSwarm(cable_length=-1.0, inertia=(0.0023, 0.0023, float("nan")))
    with pytest.raises(IncompatibleError, match="load"):
        quad3.rhs(torch.tensor(0.0), torch.zeros(1, 3, 13, dtype=F64))


# ---- full doorway flights (slow) --------------------------------------------------------------------
@pytest.mark.slow
@pytest.mark.parametrize("n_quads", [3, 6])
def test_full_doorway_flight(n_quads: int) -> None:
    """§7.5–7.9 over whole flights, with no rejection: every sampled scenario must pass the door."""
    system = QuadrotorSwarm(n_quads=n_quads)
    run = system.rollout(system.sample_scenarios(4, torch.Generator().manual_seed(11)))
    assert run.accepted.all(), {k: v.tolist() for k, v in system.failed_checks(run.checks).items()}
    # independent recomputation of the door and goal checks from the 20 Hz samples
    p, p_load = run.trajectories.x[..., :3], run.load[..., :3]
    centres = torch.tensor(DOOR_CENTRES, dtype=F64)
    quad_clear = (p[..., None, :2] - centres).norm(dim=-1).amin((-1, -2)) - DOOR_RADIUS - QUAD_RADIUS
    load_clear = (p_load[..., None, :2] - centres).norm(dim=-1).amin(-1) - DOOR_RADIUS - LOAD_RADIUS
    assert quad_clear.min() > 0 and load_clear.min() > 0
    through = (p_load[..., 0] - 3.0).abs() < 0.1  # samples near the door plane
    assert through.any(1).all() and p_load[..., 1][through].abs().max() < 0.15
    assert (p_load[:, -1] - run.scenario.goal).norm(dim=-1).max() < 0.1
    assert run.tension.min() > 0.1 and run.checks["max_cable_error"].max() < 1e-4
    assert run.trajectories.u.max() <= system.rotor_max and (run.checks["saturated_ticks"] == 0).all()


@pytest.mark.slow
def test_energy_balance_full_flight(quad3: QuadrotorSwarm) -> None:
    """§7.3 over a whole 12 s flight (prototype: about 1e-5 J error against about 60 J)."""
    scenario = quad3.sample_scenarios(2, torch.Generator().manual_seed(12))
    _, _, d_energy, work = _flight(quad3, scenario, 12.0)
    torch.testing.assert_close(d_energy, work, rtol=0, atol=1e-5)


@pytest.mark.slow
def test_integrator_converged(quad3: QuadrotorSwarm) -> None:
    """§7.10: RK4 at h = 2 ms and 0.5 ms agree to 1e-6 on the final state (3 s of closed loop)."""
    fine = QuadrotorSwarm(n_quads=3, substeps=20)
    scenario = quad3.sample_scenarios(2, torch.Generator().manual_seed(13))
    x_a, load_a, _, _ = _flight(quad3, scenario, 3.0)
    x_b, load_b, _, _ = _flight(fine, scenario, 3.0)
    torch.testing.assert_close(x_a, x_b, rtol=0, atol=1e-6)
    torch.testing.assert_close(load_a, load_b, rtol=0, atol=1e-6)
