"""The first candidate of issue 27's controller, offline only: a measured experiment, not the
product (``ballbeam run`` still uses the law in ``core/control.py``).

    .venv/bin/python bench/replanning_prototype.py                 # six cases, ~2 min
    .venv/bin/python bench/replanning_prototype.py --set plant.ball_gain_scale=1.2 \\
        --plot /tmp/candidate.png

What it does each 1 ms cycle (numpy, not the bit-exact per-cycle arithmetic of the product):

- a steady-state Kalman filter on the design model, predicting with the identified γ;
- γ identified by least squares of the measured position on the double integral of the
  measured angle over the last 0.3 s, while the servo is far from level (|θ| > 20° on
  average: at rest the regressor carries no information);
- every 10 ms a warm re-plan (``core/planning/arcs.replan``) from the **plan's own servo state
  and the estimated ball state**: the servo's small errors are the tracker's, the ball's are
  the plan's, so the plan's structure survives the estimate's noise;
- a re-plan that adds arcs (a detour: the minimum time from a state a little past the path
  jumps by tens of milliseconds) is taken only when the ball is far off (2 mm or 10 mm/s);
- no re-plan in the last 0.15 s (the final stroke: a re-plan there is a full-voltage
  micro-manoeuvre for a fraction of a millimetre);
- u = u_plan + K (x_plan − x̂) (discrete LQR on the design model), dead-zone compensated with
  the design's 0.1 V; after the plan a terminal LQR to the target.

Each case prints rest / own floor (the plan-free minimum time on the true plant: its α, γ,
5 V less its dead zone), max |θ|, the voltage's total variation, and the re-plans made and
missed. The figures and what they teach are in docs/design.md ("Issue 27: the first
re-planning candidate").
"""

from __future__ import annotations

import argparse
import math
import time
from dataclasses import dataclass

import numpy as np
import scipy.linalg

from ballbeam.config import load_config
from ballbeam.core.model import LinearModel, PhysicalConstants
from ballbeam.core.observer import design_observer
from ballbeam.core.planning.arcs import plan_arcs, replan
from ballbeam.core.planning.lag_hold import _Params
from ballbeam.core.planning.time_optimal import plan_time_optimal
from ballbeam.core.plant import PlantPhysics, initial_noise, next_noise, read_sensors
from ballbeam.errors import PlanningError
from ballbeam.plant_assembly import plant_parameters

PERIOD_S = 1e-3
THETA_LIMIT_RAD = math.radians(52.0)
PAPER = "configs/paper.toml"
CASES = {
    "nominal": [],
    "ball 0.8": ["plant.ball_gain_scale=0.8"],
    "ball 1.2": ["plant.ball_gain_scale=1.2"],
    "motor 0.9": ["plant.motor_gain_scale=0.9"],
    "dead zone 0.3": ["plant.deadzone_v=0.3"],
    "short start": ["initial.theta_deg=10.0", "initial.ball_position_m=0.03"],
}


def dlqr(Ad: np.ndarray, Bd: np.ndarray, Q: np.ndarray, R: np.ndarray) -> np.ndarray:
    P = scipy.linalg.solve_discrete_are(Ad, Bd, Q, R)
    gain: np.ndarray = np.linalg.solve(R + Bd.T @ P @ Bd, Bd.T @ P @ Ad)[0]
    return gain


def model_of(alpha: float, pole_per_s: float, gamma: float) -> LinearModel:
    C = np.array([[57.0, 0.0, 0.0, 0.0], [0.0, 0.0, 0.0, 100.0]])
    return LinearModel.from_gains(alpha=alpha, alpha_beta=pole_per_s, gamma=gamma, C=C)


def own_floor_s(
    start: np.ndarray, alpha: float, pole_per_s: float, gamma: float, dz: float
) -> float:
    model = model_of(alpha, pole_per_s, gamma)
    try:
        return plan_arcs(model, start, voltage_limit_v=5.0 - dz).duration_s
    except PlanningError:
        return plan_time_optimal(
            model, start, voltage_limit_v=5.0 - dz, theta_max_rad=THETA_LIMIT_RAD
        ).duration_s


@dataclass
class Result:
    rest_s: float
    floor_s: float
    max_theta_deg: float
    input_tv_v: float
    replans: int
    missed: int
    replan_p99_ms: float
    gamma_ratio: float
    time_s: np.ndarray
    states: np.ndarray
    voltage_v: np.ndarray
    reference: np.ndarray

    @property
    def ratio(self) -> float:
        return self.rest_s / self.floor_s


def run(overrides: list[str], extra_s: float = 3.0) -> Result:
    config = load_config(PAPER, overrides)
    params = plant_parameters(config)
    physics = PlantPhysics(params)
    rng = np.random.default_rng(config.plant.seed)
    constants = PhysicalConstants()
    pole, alpha, gamma_design = constants.alpha * constants.beta, constants.alpha, constants.gamma
    gamma = gamma_design
    deadzone_v = 0.1
    theta_plan = THETA_LIMIT_RAD - math.radians(0.5)
    x0 = config.initial.state()
    floor = own_floor_s(x0, params.alpha, params.alpha_beta, params.gamma, params.deadzone_v)
    n = int((floor + extra_s) / PERIOD_S)
    design = model_of(alpha, pole, gamma).discretize(PERIOD_S)
    observer = design_observer(
        design,
        input_noise_v=0.5,
        ball_noise_m_s2=0.05,
        angle_noise_rad=params.encoder_step_rad / math.sqrt(12.0),
        position_noise_m=2e-4,
    )
    K = dlqr(design.Ad, design.Bd, np.diag([10.0, 0.0, 0.0, 1e4]), np.array([[0.01]]))
    K_terminal = dlqr(design.Ad, design.Bd, np.diag([100.0, 0.0, 0.0, 3e4]), np.array([[1.0]]))
    start = np.array(x0, dtype=float)
    start[0] = float(np.clip(start[0], -theta_plan, theta_plan))
    plan = plan_arcs(
        model_of(alpha, pole, gamma),
        start,
        voltage_limit_v=5.0 - deadzone_v - 0.3,
        theta_max_rad=theta_plan,
    )
    plan_t0 = 0.0
    Ad, Bd = design.Ad, design.Bd[:, 0]
    state = np.array(x0, dtype=float)
    noise = initial_noise(params, rng)
    estimate = np.array(x0, dtype=float)
    drive_v = 0.0
    terminal = False
    angles: list[float] = []
    positions: list[float] = []
    states, voltages, peaks, references = [], [], [], []
    replans = missed = 0
    solve_s: list[float] = []
    for k in range(n):
        t = k * PERIOD_S
        reading = read_sensors(params, state, noise)
        theta_m = reading.angle_counts * params.encoder_step_rad
        position_m = reading.position_counts * params.adc_step_m
        y = np.array([57.0 * theta_m, 100.0 * position_m])
        if k:
            prior = Ad @ estimate + Bd * drive_v
            estimate = prior + observer.L @ (y - design.C @ prior)
        else:
            estimate = np.array([theta_m, x0[1], x0[2], position_m])
        angles.append(theta_m)
        positions.append(position_m)
        if k % 20 == 0 and k >= 100:
            window = min(300, k)
            theta_w = np.array(angles[-window:])
            if np.mean(np.abs(theta_w)) > math.radians(20.0):
                integral = np.cumsum(np.cumsum(theta_w) * PERIOD_S) * PERIOD_S
                X = np.column_stack([np.ones(window), np.arange(window) * PERIOD_S, integral])
                fit = np.linalg.lstsq(X, np.array(positions[-window:]), rcond=None)[0][2]
                if 0.5 < fit / gamma_design < 1.6:
                    gamma = 0.7 * gamma + 0.3 * fit
                    updated = model_of(alpha, pole, gamma).discretize(PERIOD_S)
                    Ad, Bd = updated.Ad, updated.Bd[:, 0]
        elapsed = t - plan_t0
        on_plan = plan.sample(np.array([elapsed])).states[0]
        if k % 10 == 0 and not terminal and elapsed < plan.duration_s - 0.15:
            began = time.perf_counter()
            from_state = np.array([on_plan[0], on_plan[1], estimate[2], estimate[3]])
            new = replan(plan, elapsed, from_state, params=_Params(pole, alpha, gamma))
            solve_s.append(time.perf_counter() - began)
            replans += 1
            far = abs(estimate[3] - on_plan[3]) > 2e-3 or abs(estimate[2] - on_plan[2]) > 0.01
            if new is None:
                missed += 1
            elif len(new.input_v) <= len(plan.shifted(elapsed)[0]) or far:
                plan, plan_t0, elapsed = new, t, 0.0
        sample = plan.sample(np.array([elapsed]))
        reference, feedforward_v = sample.states[0], float(sample.input_v[0])
        terminal = terminal or elapsed >= plan.duration_s
        if terminal:
            demand_v = -float(K_terminal @ estimate)
        else:
            demand_v = feedforward_v + float(K @ (reference - estimate))
        shift = math.copysign(deadzone_v, demand_v) if abs(demand_v) > 0.02 else 0.0
        command_v = max(-5.0, min(5.0, demand_v + shift))
        drive_v = command_v - math.copysign(min(deadzone_v, abs(command_v)), command_v)
        peak = abs(float(state[0]))
        state, step_peak = physics.advance_with_peak(
            state, command_v, config.plant.physics_substeps
        )
        noise = next_noise(params, noise, rng)
        states.append(state.copy())
        voltages.append(command_v)
        peaks.append(max(peak, step_peak))
        references.append(reference)
    trajectory = np.array(states)
    times = (np.arange(n) + 1) * PERIOD_S
    outside = np.flatnonzero(
        (np.abs(trajectory[:, 3]) > 5e-4) | (np.abs(trajectory[:, 0]) > math.radians(0.5))
    )
    rest = float(times[outside[-1]]) if outside.size else 0.0
    if outside.size and outside[-1] == n - 1:
        rest = math.inf
    return Result(
        rest_s=rest,
        floor_s=floor,
        max_theta_deg=math.degrees(max(peaks)),
        input_tv_v=float(np.sum(np.abs(np.diff(voltages)))),
        replans=replans,
        missed=missed,
        replan_p99_ms=float(np.percentile(solve_s, 99) * 1e3) if solve_s else 0.0,
        gamma_ratio=gamma / params.gamma,
        time_s=times,
        states=trajectory,
        voltage_v=np.array(voltages),
        reference=np.array(references),
    )


def plot(result: Result, path: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(3, 1, figsize=(10, 8), sharex=True)
    axes[0].plot(result.time_s, np.degrees(result.states[:, 0]), label="θ")
    axes[0].plot(result.time_s, np.degrees(result.reference[:, 0]), "--", label="plan")
    axes[0].set_ylabel("servo angle [deg]")
    axes[1].plot(result.time_s, result.states[:, 3])
    axes[1].plot(result.time_s, result.reference[:, 3], "--")
    axes[1].set_ylabel("ball position [m]")
    axes[2].plot(result.time_s, result.voltage_v)
    axes[2].set_ylabel("command [V]")
    axes[2].set_xlabel("time [s]")
    axes[0].legend()
    fig.savefig(path, dpi=80)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--set", action="append", default=[], help="one case: config overrides")
    parser.add_argument("--plot", help="with --set: write the run's plot here (PNG)")
    args = parser.parse_args()
    cases = {"custom": args.set} if args.set else CASES
    print(
        f"{'case':15} {'rest/floor':>10} {'floor s':>8} {'max|θ|°':>8} {'TV V':>7} "
        f"{'replans':>7} {'missed':>6} {'p99 ms':>7} {'γ̂/γ':>6}"
    )
    for name, overrides in cases.items():
        r = run(overrides)
        print(
            f"{name:15} {r.ratio:10.3f} {r.floor_s:8.3f} {r.max_theta_deg:8.3f} "
            f"{r.input_tv_v:7.1f} {r.replans:7d} {r.missed:6d} {r.replan_p99_ms:7.1f} "
            f"{r.gamma_ratio:6.3f}"
        )
        if args.plot and args.set:
            plot(r, args.plot)


if __name__ == "__main__":
    main()
