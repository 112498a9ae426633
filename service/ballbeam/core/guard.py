"""Servo-angle guard: keeps the servo inside ±θ_limit without chattering on the limit arcs.

Two layers, both caps on the voltage the tracker asks for (mirrored for the lower limit):

* **Soft cap** (smooth, the one that acts): the servo rate is held below an allowed rate
  ω_a(gap) that vanishes at a soft limit θ_s, gap = θ_s − θ. Far out ω_a is the exact
  full-braking curve (the rate from which braking at V_soft stops the servo at θ_s), near θ_s
  it is k·gap (a linear zone, so the cap is a plain PD law there instead of a corner). The cap
  is the voltage that makes θ̇ follow ω_a with a first-order rate loop of gain κ::

      α·u_cap = αβ·θ̇ − ω_a'(gap)·θ̇ + κ (ω_a − θ̇)

  It is continuous in the state (piecewise linear), so estimate noise moves it by small
  amounts instead of flipping it between ±V; on the braking curve it equals −V_soft.
* **Hard barrier** (the safety net, idle in normal running): the safe set is
  {θ + d(θ̇) <= θ_limit}, d the exact stopping distance of the motor model
  θ̈ = −αβ·θ̇ − α·V_brake under full braking. Each cycle the largest (smallest) voltage whose
  one-period successor stays in the safe set is found; the successor is linear in u and d is
  increasing, so the bound is a monotone 1-D root. It is a dead-beat law: it acts only if the
  soft cap was overrun (model error, a disturbance).

The cycle runs in plain float arithmetic (a recorded run must replay bit for bit on any CPU,
and libm's logarithm is not the same on every machine): d and ω_a come from tables computed at
design time and interpolated linearly. d is convex, so its chords lie above it: the table
never promises a shorter stop than the motor gives; ω_a (d's inverse) is concave, so its
chords lie below it: the allowed rate is never more than the braking curve's.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ballbeam.core.model import Row4, as_row4

BISECTION_STEPS = 40
STOPPING_TABLE_STEP_RAD_S = 0.01  # interpolation error ≤ step²/(8·α·V_brake) ≈ 2e-8 rad
STOPPING_TABLE_SLEW_MULTIPLE = 3.0  # the table covers 3× the motor's top speed
ALLOWED_RATE_POINTS = 256  # ω_a(gap) over gaps 0..2·θ_s
# Real time: the look-aheads beyond the design's latency allowance the hard barrier can take on
# when the loop runs later than that allowance [ns]; a lateness between two steps takes the
# longer one (never less look-ahead than measured).
LATENESS_STEPS_NS = (250_000, 500_000, 1_000_000, 2_000_000, 4_000_000, 8_000_000,
                     16_000_000, 32_000_000)
# What a cycle's computation adds to its start lateness before its command is out [ns]
# (measured: 40–200 µs a cycle).
COMPUTE_ALLOWANCE_NS = 250_000



@dataclass(frozen=True)
class SoftCap:
    """The smooth cap: ``allowed_rate_rad_s[i]`` = ω_a(i·gap_step_rad) on the braking curve at
    V_soft (beyond the table: its last value); the motor model α, αβ."""

    theta_limit_rad: float  # θ_s: where the allowed rate reaches zero
    zone_gain_per_s: float  # k: ω_a = k·gap near θ_s
    rate_gain_per_s: float  # κ: how hard the rate is pulled back onto ω_a
    alpha: float
    alpha_beta: float
    gap_step_rad: float
    allowed_rate_rad_s: tuple[float, ...]


@dataclass(frozen=True)
class AngleGuard:
    """The guard as the cycle runs it: plain floats, recorded with the design.

    ``theta_row``/``rate_row``: θ and θ̇ after the look-ahead per unit of each state (the first
    two rows of Ad over one period, plus the latency in real time); ``theta_per_v``/
    ``rate_per_v``: the same per volt (Bd). ``stopping_rad[i]``: stopping distance from
    rate ``i·rate_step_rad_s``; beyond the table it grows by ``beyond_slope_s`` per rad/s
    (1/αβ, the largest slope d can have).
    """

    theta_limit_rad: float  # the angle the servo must not pass (limit minus a margin)
    voltage_limit_v: float
    theta_row: Row4
    rate_row: Row4
    theta_per_v: float
    rate_per_v: float
    rate_step_rad_s: float
    stopping_rad: tuple[float, ...]
    beyond_slope_s: float
    soft: SoftCap | None = None
    # Real time: the look-ahead follows the lateness the loop measures (see LatenessWatch).
    # ``lateness_steps``: (extra look-ahead [ns], then the servo's response over it: θ per θ̇,
    # θ per volt, θ̇ per θ̇, θ̇ per volt); empty: off (offline, lock-step, older logs).
    lateness_steps: tuple[tuple[float, float, float, float, float], ...] = ()
    lateness_allowance_ns: int = 0  # what the design's look-ahead already covers
    lateness_hold_cycles: int = 0  # how long a measured lateness is kept as the worst
    # The watch's two buckets (see LatenessWatch); False: a log from before them, replayed
    # with the single worst it kept then.
    lateness_buckets: bool = True
    # The lateness the loop measured just before the run (the daemon's probe): the watch starts
    # with it as its first bucket's worst, so it is kept as margin as long as a lateness
    # measured in the run, then let go (0: nothing measured; older logs).
    lateness_start_ns: int = 0


@dataclass(frozen=True)
class LatenessWatch:
    """The worst recent lateness of the loop [ns]: each cycle's start lateness plus the periods
    it skipped (what the previous command was held beyond its period), over at least the last
    ``lateness_hold_cycles`` cycles (at most twice that). Two buckets of that many cycles: the
    worst is that of the current one and the one before. Pure: a replay computes the same from
    the log's /timing.

    Logs from before the buckets kept only the worst and its age, and let it go when it aged
    out, forgetting whatever came later but was smaller: a run's watch dropped from 3.8 ms to
    90 µs though the loop had been 3 ms late 150 cycles before, and the dead-zone learning
    resumed on that and learnt 0.03 V for the plant's 0.1 V (unprivileged, under load)."""

    worst_ns: int = 0
    age_cycles: int = 0  # cycles into the current bucket (before the buckets: the worst's age)
    bucket_ns: int = 0  # the current bucket's worst
    previous_ns: int = 0  # the previous bucket's worst


NO_LATENESS = LatenessWatch()


def starting_watch(guard: AngleGuard | None) -> LatenessWatch:
    """The watch a run starts with: the lateness measured before it, in its first bucket."""
    if guard is None or not guard.lateness_steps or not guard.lateness_start_ns:
        return NO_LATENESS
    start_ns = guard.lateness_start_ns
    return LatenessWatch(worst_ns=start_ns, age_cycles=0, bucket_ns=start_ns, previous_ns=0)


def watch_lateness(
    guard: AngleGuard | None, watch: LatenessWatch, lateness_ns: int
) -> LatenessWatch:
    """``watch`` after a cycle that started ``lateness_ns`` late (skipped periods included)."""
    if guard is None or not guard.lateness_steps:
        return watch
    if not guard.lateness_buckets:
        if lateness_ns >= watch.worst_ns or watch.age_cycles >= guard.lateness_hold_cycles:
            return LatenessWatch(lateness_ns, 0)
        return LatenessWatch(watch.worst_ns, watch.age_cycles + 1)
    bucket_ns, previous_ns, age = watch.bucket_ns, watch.previous_ns, watch.age_cycles
    if age >= guard.lateness_hold_cycles:
        bucket_ns, previous_ns, age = 0, bucket_ns, 0
    bucket_ns = max(bucket_ns, lateness_ns)
    return LatenessWatch(max(bucket_ns, previous_ns), age + 1, bucket_ns, previous_ns)


def lateness_step(
    guard: AngleGuard, worst_ns: int
) -> tuple[float, float, float, float, float] | None:
    """The look-ahead step for a worst lateness: None while the design's allowance covers it."""
    extra_ns = worst_ns + COMPUTE_ALLOWANCE_NS - guard.lateness_allowance_ns
    if extra_ns <= 0 or not guard.lateness_steps:
        return None
    for step in guard.lateness_steps:
        if step[0] >= extra_ns:
            return step
    return guard.lateness_steps[-1]


def make_lateness_steps(
    alpha: float, alpha_beta: float
) -> tuple[tuple[float, float, float, float, float], ...]:
    """The servo's exact response over each extra look-ahead e, with the voltage held:
    θ̇(e) = c·θ̇ + d·u, θ(e) = θ + a·θ̇ + b·u, with c = e^(−αβe), a = (1 − c)/αβ,
    d = (α/αβ)(1 − c), b = (α/αβ)(e − a). Computed here, once: the cycle uses no libm."""
    steps = []
    speed_per_v = alpha / alpha_beta
    for extra_ns in LATENESS_STEPS_NS:
        extra_s = extra_ns * 1e-9
        decay = math.exp(-alpha_beta * extra_s)
        a = (1.0 - decay) / alpha_beta
        steps.append((float(extra_ns), a, speed_per_v * (extra_s - a), decay,
                      speed_per_v * (1.0 - decay)))
    return tuple(steps)


def exact_stopping_distance_rad(
    alpha: float, alpha_beta: float, brake_v: float, rate_rad_s: np.ndarray
) -> np.ndarray:
    """Angle travelled from rate ω > 0 until rest under full braking (0 for ω <= 0).

    ω̇ = −aω − c with a = αβ, c = α·V_brake: stops at t* = ln(1 + aω/c)/a after
    d = ω/a − (c/a²)·ln(1 + aω/c)."""
    a, c = alpha_beta, alpha * brake_v
    rate = np.maximum(np.asarray(rate_rad_s, dtype=float), 0.0)
    result: np.ndarray = rate / a - (c / (a * a)) * np.log1p(a * rate / c)
    return result


def make_angle_guard(
    *,
    theta_limit_rad: float,
    alpha: float,
    alpha_beta: float,
    brake_v: float,
    voltage_limit_v: float,
    Ad: np.ndarray,
    Bd: np.ndarray,
    soft: SoftCap | None = None,
    lateness_allowance_ns: int = 0,
    lateness_hold_cycles: int = 0,
    lateness_start_ns: int = 0,
) -> AngleGuard:
    """The guard for a motor model (α, αβ), a braking voltage and a look-ahead (Ad, Bd);
    ``lateness_hold_cycles`` > 0: the look-ahead follows the measured lateness beyond
    ``lateness_allowance_ns`` (real time), starting from ``lateness_start_ns``."""
    top_rate = STOPPING_TABLE_SLEW_MULTIPLE * voltage_limit_v * alpha / alpha_beta
    count = math.ceil(top_rate / STOPPING_TABLE_STEP_RAD_S) + 1
    rates = np.arange(count) * STOPPING_TABLE_STEP_RAD_S
    table = exact_stopping_distance_rad(alpha, alpha_beta, brake_v, rates)
    return AngleGuard(
        theta_limit_rad=float(theta_limit_rad),
        voltage_limit_v=float(voltage_limit_v),
        theta_row=as_row4(Ad[0]),
        rate_row=as_row4(Ad[1]),
        theta_per_v=float(Bd[0, 0]),
        rate_per_v=float(Bd[1, 0]),
        rate_step_rad_s=STOPPING_TABLE_STEP_RAD_S,
        stopping_rad=tuple(table.tolist()),
        beyond_slope_s=1.0 / alpha_beta,
        soft=soft,
        lateness_steps=make_lateness_steps(alpha, alpha_beta) if lateness_hold_cycles else (),
        lateness_allowance_ns=lateness_allowance_ns if lateness_hold_cycles else 0,
        lateness_hold_cycles=lateness_hold_cycles,
        lateness_start_ns=lateness_start_ns if lateness_hold_cycles else 0,
    )


def make_soft_cap(
    *,
    theta_limit_rad: float,
    alpha: float,
    alpha_beta: float,
    brake_v: float,
    zone_gain_per_s: float,
    rate_gain_per_s: float,
    reaction_s: float = 0.0,
) -> SoftCap:
    """The soft cap at ±``theta_limit_rad``: ω_a(gap) solves ω·t_r + d(ω) = gap on a uniform
    gap grid (increasing in ω: by bisection here, at design time). ``reaction_s`` (t_r): how
    long a command may come late beyond the period, the servo running on meanwhile; 0 on a
    loop that keeps time."""
    gap_step = 2.0 * theta_limit_rad / (ALLOWED_RATE_POINTS - 1)
    gaps = np.arange(ALLOWED_RATE_POINTS) * gap_step

    def distance(rate: np.ndarray) -> np.ndarray:
        travelled: np.ndarray = rate * reaction_s + exact_stopping_distance_rad(
            alpha, alpha_beta, brake_v, rate
        )
        return travelled

    low, high = np.zeros_like(gaps), np.ones_like(gaps)
    while np.any(short := distance(high) < gaps):
        high = np.where(short, 2.0 * high, high)
    for _ in range(80):
        middle = 0.5 * (low + high)
        inside = distance(middle) <= gaps
        low, high = np.where(inside, middle, low), np.where(inside, high, middle)
    return SoftCap(
        theta_limit_rad=float(theta_limit_rad),
        zone_gain_per_s=float(zone_gain_per_s),
        rate_gain_per_s=float(rate_gain_per_s),
        alpha=float(alpha),
        alpha_beta=float(alpha_beta),
        gap_step_rad=float(gap_step),
        allowed_rate_rad_s=tuple(low.tolist()),
    )


def soft_cap_v(soft: SoftCap, theta_rad: float, rate_rad_s: float) -> float:
    """The soft cap on u toward +θ_s for the state (θ, θ̇) (mirror the state for −θ_s)."""
    gap = soft.theta_limit_rad - theta_rad
    allowed = soft.zone_gain_per_s * gap
    slope = soft.zone_gain_per_s
    if gap > 0.0:
        table = soft.allowed_rate_rad_s
        position = gap / soft.gap_step_rad
        last = len(table) - 1
        if position < last:
            index = int(position)
            low = table[index]
            rise = table[index + 1] - low
            curve = low + (position - index) * rise
            curve_slope = rise / soft.gap_step_rad
        else:
            curve, curve_slope = table[last], 0.0
        if curve < allowed:
            allowed, slope = curve, curve_slope
    # θ̈ = −αβ θ̇ + α u is asked to be dω_a/dt + κ (ω_a − θ̇), with dω_a/dt = −ω_a'·θ̇.
    accel = -slope * rate_rad_s + soft.rate_gain_per_s * (allowed - rate_rad_s)
    return (soft.alpha_beta * rate_rad_s + accel) / soft.alpha


def stopping_distance_rad(guard: AngleGuard, rate_rad_s: float) -> float:
    """The table's stopping distance from ``rate_rad_s`` (0 for a rate <= 0)."""
    if rate_rad_s <= 0.0:
        return 0.0
    table = guard.stopping_rad
    position = rate_rad_s / guard.rate_step_rad_s
    last = len(table) - 1
    if not position < last:  # beyond the table (or NaN: no stop is promised)
        if position != position:
            return math.inf
        return table[last] + (rate_rad_s - last * guard.rate_step_rad_s) * guard.beyond_slope_s
    index = int(position)
    fraction = position - index
    return table[index] + fraction * (table[index + 1] - table[index])


def guarded_voltage(
    guard: AngleGuard, estimate: Row4, requested_v: float, worst_lateness_ns: int = 0
) -> float:
    """``requested_v`` clamped to ±V, to the soft cap and to the hard barrier's safe interval.
    ``worst_lateness_ns`` (real time, LatenessWatch): a loop later than the design allowed for
    holds each command longer; the barrier then looks that much further ahead."""
    x0, x1, x2, x3 = estimate
    limit = guard.voltage_limit_v
    voltage = min(max(requested_v, -limit), limit)
    soft = guard.soft
    if soft is not None:
        voltage = min(voltage, soft_cap_v(soft, x0, x1))
        voltage = max(voltage, -soft_cap_v(soft, -x0, -x1))
        voltage = min(max(voltage, -limit), limit)
    t0, t1, t2, t3 = guard.theta_row
    r0, r1, r2, r3 = guard.rate_row
    # The successor is (free response) + Bd·u; the free part once per cycle.
    theta_free = t0 * x0 + t1 * x1 + t2 * x2 + t3 * x3
    rate_free = r0 * x0 + r1 * x1 + r2 * x2 + r3 * x3
    theta_per_v = guard.theta_per_v
    rate_per_v = guard.rate_per_v
    step = lateness_step(guard, worst_lateness_ns) if guard.lateness_steps else None
    if step is not None:  # the servo runs on, the voltage held, for the extra time
        _, a, b, c, d = step
        theta_free, rate_free = theta_free + a * rate_free, c * rate_free
        theta_per_v, rate_per_v = theta_per_v + a * rate_per_v + b, c * rate_per_v + d

    def margin(input_v: float, sign: float) -> float:
        """Distance left to the limit (side ``sign``) after one period at ``input_v``."""
        theta = theta_free + theta_per_v * input_v
        rate = rate_free + rate_per_v * input_v
        return guard.theta_limit_rad - sign * theta - stopping_distance_rad(guard, sign * rate)

    for sign in (1.0, -1.0):
        # Pushing toward the limit on side `sign` means voltage·sign large.
        if margin(voltage, sign) >= 0.0:
            continue
        safest = -sign * limit
        if margin(safest, sign) < 0.0:
            return safest  # cannot stay inside: brake as hard as possible
        inside, outside = safest, voltage
        for _ in range(BISECTION_STEPS):
            middle = 0.5 * (inside + outside)
            if margin(middle, sign) >= 0.0:
                inside = middle
            else:
                outside = middle
        voltage = inside
    return voltage
