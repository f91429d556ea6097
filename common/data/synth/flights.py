"""Trajectory families beyond the ring orbit: figure-eight, lawnmower, inward-looking orbits,
vertical sweeps, and two modifiers (hover-then-go start, aggressive segments).

``recslam dataset synth --flight FAMILY[+MODIFIER...]`` picks them (:func:`parse_flight`):

- ``ring`` (default): today's outward-looking loops (:mod:`common.data.synth.trajectory`),
  untouched; with a modifier it is drawn here as an outward-looking ellipse orbit.
- ``figure8``: a Lissajous figure-eight ``(A sin th, B sin 2th)`` through the middle of the
  flight region; the camera looks sideways (heading +/- 90 degrees, the sign following the
  direction of travel, so robots flying either way see the same places the same way).
- ``lawnmower``: rows along x (a three-harmonic triangle wave: straight legs, smooth turns)
  shifted across y by a slow sweep; yaw nearly fixed (no turn at the row ends), camera
  pitched down towards the floor and the far wall.
- ``inward``: an ellipse orbit with the camera looking at the region's centre.
- ``vertical``: a slow outward-looking orbit with fast up-and-down sweeps (triangle wave in z).
- ``+hover``: the start as in EuRoC: a few seconds (``FlightConfig.hover_s``) nearly still,
  ``tau'(t) = (1 + erf((t - t_go) / T)) / 2`` (speed at ``t = 0`` below 1e-7 of cruise).
- ``+aggressive``: Gaussian bursts of the time warp ``tau'(t) += g_i exp(-((t - c_i)/s_i)^2)``
  every few seconds, each gain sized so that the burst reaches ``aggressive_speed`` or
  ``aggressive_rate`` (about 2 m/s, 2.5 rad/s) unless ``aggressive_accel`` (6 m/s^2) binds
  first; the path is unchanged, only flown faster.

Every flight is a path of sinusoids in a warped time ``tau(t)`` (:class:`Warp`, closed form
with an erf), so position, velocity, acceleration, attitude and body rates are analytic and
C-infinity; each robot's mean speed is set (``FlightConfig.mean_speed``, slow robot 0 to fast
robot n-1) by scaling the path's frequencies. Robots of one dataset fly the same family in the
same region with their own phases, so their places overlap. Every flight is checked with
:func:`~common.data.synth.trajectory.check_trajectory` (clearance, speed, rate) and redrawn
when it fails.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field, replace

import numpy as np
from scipy.special import erf

from common.data.synth.scene import Scene
from common.data.synth.trajectory import (
    T_IMU_CAM,
    LoopTrajectory,
    Region,
    TrajectoryConfig,
    TrajectoryError,
    TrajectoryState,
    Wave,
    check_trajectory,
    look_attitude,
    make_trajectories,
)

FAMILIES = ("ring", "figure8", "lawnmower", "inward", "vertical")
MODIFIERS = ("hover", "aggressive")


@dataclass(frozen=True)
class FlightSpec:
    """A family and its modifiers; ``name`` is the canonical ``family[+modifier...]``."""

    family: str = "ring"
    hover: bool = False
    aggressive: bool = False

    @property
    def name(self) -> str:
        mods = [m for m in MODIFIERS if getattr(self, m)]
        return "+".join([self.family, *mods])

    @property
    def is_default(self) -> bool:
        return self == FlightSpec()


def parse_flight(text: str) -> FlightSpec:
    """``"figure8+aggressive"``, ``"lawnmower"``, ``"hover"`` (= ``ring+hover``) ... ->
    :class:`FlightSpec`; TrajectoryError naming the unknown word."""
    words = [w.strip().lower() for w in text.split("+") if w.strip()]
    family = "ring"
    mods: set[str] = set()
    for i, w in enumerate(words):
        if w in FAMILIES and i == 0:
            family = w
        elif w in MODIFIERS:
            mods.add(w)
        else:
            raise TrajectoryError(
                f"--flight {text!r}: {w!r} is not a family ({', '.join(FAMILIES)}; first) "
                f"or a modifier ({', '.join(MODIFIERS)})"
            )
    return FlightSpec(family, "hover" in mods, "aggressive" in mods)


@dataclass(frozen=True)
class FlightConfig:
    """Limits and style of the families.

    ``mean_speed``: mean speed [m/s] of robot 0 and of robot n-1 (others between);
    ``limits``: clearance, top speed and rate every flight must keep (redrawn if not);
    ``aggressive_speed`` [m/s] / ``aggressive_rate`` [rad/s]: what the bursts aim at and the
    limits of aggressive flights; ``aggressive_accel`` [m/s^2]: their acceleration limit (a
    burst at a sharp turn is smaller); ``burst_every_s`` / ``burst_width_s``: spacing and width of
    the bursts [s]; ``hover_s``: range of the still start [s]; ``hover_ramp_s``: its ramp
    time constant [s]; ``attempts``: redraws before giving up.
    """

    mean_speed: tuple[float, float] = (0.45, 0.85)
    limits: TrajectoryConfig = field(
        default_factory=lambda: TrajectoryConfig(max_speed=1.4, max_rate=1.6)
    )
    aggressive_speed: float = 2.0
    aggressive_rate: float = 2.5
    aggressive_accel: float = 6.0
    burst_every_s: tuple[float, float] = (5.0, 8.0)
    burst_width_s: tuple[float, float] = (0.5, 0.8)
    hover_s: tuple[float, float] = (3.0, 5.0)
    hover_ramp_s: float = 0.8
    attempts: int = 60

    def check_limits(self, spec: FlightSpec) -> TrajectoryConfig:
        """The limits a flight of ``spec`` is checked against."""
        if not spec.aggressive:
            return self.limits
        return replace(self.limits, max_speed=self.aggressive_speed, max_rate=self.aggressive_rate)


@dataclass(frozen=True)
class Warp:
    """Warped time ``tau(t)`` [s] with ``tau(0) = 0``: a start (``go_s == 0``: the ring's
    ``tau' = 1 - exp(-(t/T)^2)``, ``T = ramp_s``; else ``(1 + erf((t - go_s)/T)) / 2``) plus
    Gaussian bursts ``g exp(-((t - c)/s)^2)`` at ``burst_t`` with widths and gains."""

    ramp_s: float = 1.5
    go_s: float = 0.0
    burst_t: tuple[float, ...] = ()
    burst_width: tuple[float, ...] = ()
    burst_gain: tuple[float, ...] = ()

    def __call__(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(tau, dtau/dt, d2tau/dt2) at ``t`` (K,) [s]."""
        t = np.asarray(t, dtype=np.float64)
        T = self.ramp_s
        if T <= 0:
            tau, w1, w2 = t.copy(), np.ones_like(t), np.zeros_like(t)
        elif self.go_s <= 0:
            e = np.exp(-((t / T) ** 2))
            tau, w1, w2 = t - T * np.sqrt(np.pi) / 2.0 * erf(t / T), 1.0 - e, 2.0 * t / T**2 * e
        else:

            def prim(x: np.ndarray | float) -> np.ndarray:
                return x * erf(x) + np.exp(-np.square(x)) / np.sqrt(np.pi)

            x = (t - self.go_s) / T
            tau = t / 2.0 + T / 2.0 * (prim(x) - prim(-self.go_s / T))
            w1 = (1.0 + erf(x)) / 2.0
            w2 = np.exp(-(x**2)) / (T * np.sqrt(np.pi))
        for c, s, g in zip(self.burst_t, self.burst_width, self.burst_gain, strict=True):
            x = (t - c) / s
            b = np.exp(-(x**2))
            tau = tau + g * s * np.sqrt(np.pi) / 2.0 * (erf(x) - erf(-c / s))
            w1 = w1 + g * b
            w2 = w2 - 2.0 * g * x / s * b
        return tau, w1, w2


def _triangle(c: float, amp: float, freq: float, phase: float) -> Wave:
    """Three-harmonic triangle wave around ``c``: straight legs and smooth turns."""
    k = 8.0 / np.pi**2
    return Wave(
        c,
        0.0,
        (amp * k, -amp * k / 9.0, amp * k / 25.0),
        (freq, 3.0 * freq, 5.0 * freq),
        (phase, 3.0 * phase, 5.0 * phase),
    )


def _scaled(w: Wave, rate: float) -> Wave:
    """``w`` with every frequency (and its drift) times ``rate``: the same path, faster."""
    return replace(w, b=w.b * rate, freq=tuple(f * rate for f in w.freq))


@dataclass(frozen=True)
class PathFlight:
    """A flight of :mod:`flights`: position ``(x, y, z)(tau)``, yaw from ``look`` plus
    ``yaw_offset``, ``pitch`` (> 0 looks down) and ``roll``, all of ``tau = warp(t)``.

    ``look``: ``"heading"`` (yaw along the horizontal direction of travel), ``"outward"`` /
    ``"centre"`` (away from / towards ``look_at``), ``"fixed"`` (yaw = ``yaw_offset`` only).
    """

    family: str
    x: Wave
    y: Wave
    z: Wave
    look: str
    look_at: tuple[float, float]
    yaw_offset: Wave
    pitch: Wave
    roll: Wave
    warp: Warp
    T_imu_cam: tuple[tuple[float, ...], ...] = tuple(map(tuple, T_IMU_CAM))

    def evaluate(self, t: np.ndarray) -> TrajectoryState:
        """Closed-form state at times ``t`` (K,) [s]."""
        t = np.atleast_1d(np.asarray(t, dtype=np.float64))
        tau, w1, w2 = self.warp(t)
        (x, x1, x2), (y, y1, y2), (z, z1, z2) = self.x(tau), self.y(tau), self.z(tau)
        p = np.stack([x, y, z], axis=1)
        d1 = np.stack([x1, y1, z1], axis=1)
        d2 = np.stack([x2, y2, z2], axis=1)
        v = d1 * w1[:, None]
        a = d2 * (w1**2)[:, None] + d1 * w2[:, None]
        if self.look == "heading":
            X, Y, Xd, Yd = x1, y1, x2, y2
        elif self.look in ("outward", "centre"):
            X, Y, Xd, Yd = x - self.look_at[0], y - self.look_at[1], x1, y1
        else:
            X, Y, Xd, Yd = np.ones_like(x), np.zeros_like(x), np.zeros_like(x), np.zeros_like(x)
        base = np.arctan2(Y, X) + (np.pi if self.look == "centre" else 0.0)
        base1 = (X * Yd - Y * Xd) / (X**2 + Y**2)
        yo, yo1, _ = self.yaw_offset(tau)
        pt, pt1, _ = self.pitch(tau)
        rl, rl1, _ = self.roll(tau)
        R, omega = look_attitude(
            base + yo, (base1 + yo1) * w1, pt, pt1 * w1, rl, rl1 * w1, np.asarray(self.T_imu_cam)
        )
        return TrajectoryState(t, p, v, a, R, omega)


Ranges = list[tuple[float, float]]


def _rw(rng: np.random.Generator, c: float, amps: Ranges, freqs: Ranges) -> Wave:
    """Random sinusoids around ``c``: amplitudes and frequencies drawn from ranges."""
    amp = tuple(float(rng.uniform(*r)) for r in amps)
    freq = tuple(float(rng.uniform(*r)) for r in freqs)
    phase = tuple(float(rng.uniform(0, 2 * np.pi)) for _ in amps)
    return Wave(float(c), 0.0, amp, freq, phase)


Drawer = Callable[[np.ndarray, np.ndarray, float, float, np.random.Generator], PathFlight]


def _attitude_waves(
    rng: np.random.Generator, agg: float, pitch_c: tuple[float, float]
) -> tuple[Wave, Wave]:
    pitch = _rw(rng, rng.uniform(*pitch_c), [(0.03, 0.08), (0.0, 0.03 * agg)], [(0.2, 0.5), (1, 2)])
    roll = _rw(rng, 0.0, [(0.03, 0.07), (0.0, 0.03 * agg)], [(0.2, 0.5), (1.0, 2.5)])
    return pitch, roll


def _height(rng: np.random.Generator, lo: np.ndarray, hi: np.ndarray) -> Wave:
    mid = (lo[2] + hi[2]) / 2.0
    return _rw(rng, mid + rng.uniform(-0.3, 0.1), [(0.1, 0.3)], [(0.15, 0.35)])


def _figure8(
    lo: np.ndarray, hi: np.ndarray, agg: float, direction: float, rng: np.random.Generator
) -> PathFlight:
    """Figure-eight through the middle of ``lo`` .. ``hi``, looking sideways (a drawer: robot
    aggressiveness ``agg`` 0.4-1 scales the wiggles, ``direction`` +-1 the sense of travel)."""
    c, half = (lo + hi) / 2.0, (hi - lo) / 2.0
    ax, ay = rng.uniform(0.5, 0.62) * half[0], rng.uniform(0.45, 0.6) * half[1]
    ph = rng.uniform(0, 2 * np.pi)
    w = direction * 0.3
    jx, jy = rng.uniform(0.02, 0.06, 2) * agg
    x = Wave(c[0], 0.0, (ax, jx), (w, rng.uniform(1, 2)), (ph, 0.0))
    y = Wave(c[1], 0.0, (ay, jy), (2 * w, rng.uniform(1, 2)), (2 * ph, 1.0))
    yaw = _rw(rng, direction * np.pi / 2 + rng.uniform(-0.25, 0.25), [(0.05, 0.2)], [(0.2, 0.5)])
    pitch, roll = _attitude_waves(rng, agg, (0.08, 0.25))
    return PathFlight(
        "figure8", x, y, _height(rng, lo, hi), "heading", (c[0], c[1]), yaw, pitch, roll, Warp()
    )


def _lawnmower(
    lo: np.ndarray, hi: np.ndarray, agg: float, direction: float, rng: np.random.Generator
) -> PathFlight:
    """Rows along x, swept across y, yaw nearly fixed towards +y, pitched down."""
    c, half = (lo + hi) / 2.0, (hi - lo) / 2.0
    w = direction * 0.3
    x = _triangle(c[0], rng.uniform(0.55, 0.68) * half[0], w, rng.uniform(0, 2 * np.pi))
    y = Wave(
        c[1] - 0.15 * half[1],
        0.0,
        (rng.uniform(0.35, 0.45) * half[1],),
        (w / 3.3,),
        (rng.uniform(0, 2 * np.pi),),
    )
    yaw = _rw(rng, np.pi / 2 + rng.uniform(-0.12, 0.12), [(0.04, 0.1)], [(0.1, 0.3)])
    pitch, roll = _attitude_waves(rng, agg, (0.35, 0.55))
    return PathFlight(
        "lawnmower", x, y, _height(rng, lo, hi), "fixed", (c[0], c[1]), yaw, pitch, roll, Warp()
    )


def _orbit(look: str, family: str) -> Drawer:
    """Drawer of an ellipse orbit looking ``look`` (``vertical``: slower, with z sweeps)."""

    def draw(
        lo: np.ndarray, hi: np.ndarray, agg: float, direction: float, rng: np.random.Generator
    ) -> PathFlight:
        c, half = (lo + hi) / 2.0, (hi - lo) / 2.0
        rx, ry = rng.uniform(0.45, 0.62) * half[0], rng.uniform(0.42, 0.6) * half[1]
        ph, w = rng.uniform(0, 2 * np.pi), direction * 0.3
        jx, jy = rng.uniform(0.02, 0.06, 2) * agg
        x = Wave(c[0], 0.0, (rx, jx), (w, 1.3), (ph + np.pi / 2, 0.0))
        y = Wave(c[1], 0.0, (ry, jy), (w, 1.7), (ph, 0.5))
        if family == "vertical":
            span = hi[2] - lo[2]
            z = _triangle((lo[2] + hi[2]) / 2.0, rng.uniform(0.24, 0.27) * span, 3.0 * w, ph)
            x, y = _scaled(x, 0.8), _scaled(y, 0.8)
        else:
            z = _height(rng, lo, hi)
        pitch_c = (0.12, 0.3) if look == "centre" else (0.08, 0.25)
        yaw = _rw(rng, rng.uniform(-0.3, 0.3), [(0.1, 0.25)], [(0.2, 0.5)])
        pitch, roll = _attitude_waves(rng, agg, pitch_c)
        return PathFlight(family, x, y, z, look, (c[0], c[1]), yaw, pitch, roll, Warp())

    return draw


DRAWERS: dict[str, Drawer] = {
    "ring": _orbit("outward", "ring"),
    "figure8": _figure8,
    "lawnmower": _lawnmower,
    "inward": _orbit("centre", "inward"),
    "vertical": _orbit("outward", "vertical"),
}


def _at_speed(f: PathFlight, seconds: float, speed: float) -> PathFlight:
    """``f`` with its frequencies scaled so that its mean speed over ``seconds`` is ``speed``."""
    tau = np.arange(0.0, seconds + 1e-9, 0.05)
    unit = replace(f, warp=Warp(ramp_s=0.0))
    rate = 1.0
    for _ in range(3):  # a path flown faster covers more of itself in ``seconds``
        g = _rescale(unit, rate)
        rate *= speed / np.linalg.norm(g.evaluate(tau).v_world_body, axis=1).mean()
    return _rescale(f, rate)


def _rescale(f: PathFlight, rate: float) -> PathFlight:
    return replace(
        f,
        x=_scaled(f.x, rate),
        y=_scaled(f.y, rate),
        z=_scaled(f.z, rate),
        yaw_offset=_scaled(f.yaw_offset, rate),
        pitch=_scaled(f.pitch, rate),
        roll=_scaled(f.roll, rate),
    )


def _bursts(
    f: PathFlight, seconds: float, rng: np.random.Generator, cfg: FlightConfig
) -> PathFlight:
    """``f`` with aggressive bursts: each burst's gain brings the top speed, rate (to 95 %) or
    acceleration (to 60 %, the burst's own change of pace adds to it) of the stretch of path it
    flies to the aggressive limits; bursts that would add less than 5 % are left out."""
    unit = replace(f, warp=Warp(ramp_s=0.0))
    start = f.warp.go_s + 2.0 * f.warp.ramp_s + 1.0
    warp = f.warp
    c = start + rng.uniform(0.5, 2.0)
    while c < seconds - 0.5:
        width = float(rng.uniform(*cfg.burst_width_s))
        # Unit-rate speed, rate and acceleration over the path the burst will fly (about
        # +-1.5 widths, at up to twice the speed): the burst is sized by their maxima.
        tau_c, w1, _ = warp(np.array([c]))
        span = np.linspace(tau_c[0] - 1.5 * width * w1[0], tau_c[0] + 3.0 * width * w1[0], 40)
        st = unit.evaluate(span)
        v = float(np.linalg.norm(st.v_world_body, axis=1).max()) * w1[0]
        r = float(np.linalg.norm(st.omega_body, axis=1).max()) * w1[0]
        acc = float(np.linalg.norm(st.a_world_body, axis=1).max()) * w1[0] ** 2
        factor = min(
            0.95 * cfg.aggressive_speed / v,
            0.95 * cfg.aggressive_rate / r,
            np.sqrt(0.6 * cfg.aggressive_accel / max(acc, 1e-9)),
        )
        if factor > 1.05:
            warp = replace(
                warp,
                burst_t=(*warp.burst_t, float(c)),
                burst_width=(*warp.burst_width, width),
                burst_gain=(*warp.burst_gain, float((factor - 1.0) * w1[0])),
            )
        c += rng.uniform(*cfg.burst_every_s)
    return replace(f, warp=warp)


def _check_accel(f: PathFlight, seconds: float, limit: float) -> str | None:
    """Why ``f``'s acceleration exceeds ``limit`` [m/s^2] over ``[0, seconds]``, or None."""
    st = f.evaluate(np.arange(0.0, seconds + 1e-9, 0.01))
    top = float(np.linalg.norm(st.a_world_body, axis=1).max())
    return None if top <= limit else f"acceleration {top:.2f} m/s^2 > {limit}"


def draw_flight(
    region: Region,
    spec: FlightSpec,
    k: int,
    n: int,
    seconds: float,
    rng: np.random.Generator,
    cfg: FlightConfig,
) -> PathFlight:
    """One random flight of ``spec`` for robot ``k`` of ``n`` in ``region``."""
    lo, hi = np.array(region[0], float), np.array(region[1], float)
    frac = k / max(n - 1, 1)
    direction = 1.0 if k % 2 == 0 else -1.0
    f = DRAWERS[spec.family](lo, hi, 0.4 + 0.6 * frac, direction, rng)
    slow, fast = cfg.mean_speed
    f = _at_speed(f, seconds, slow + (fast - slow) * frac * rng.uniform(0.85, 1.0))
    if spec.hover:
        f = replace(f, warp=Warp(cfg.hover_ramp_s, float(rng.uniform(*cfg.hover_s))))
    else:
        f = replace(f, warp=Warp(1.5))
    if spec.aggressive:
        f = _bursts(f, seconds, rng, cfg)
    return f


def make_flights(
    scene: Scene,
    region: Region,
    spec: FlightSpec,
    robots: int,
    seconds: float,
    seed: int,
    ring: TrajectoryConfig | None = None,
    cfg: FlightConfig | None = None,
) -> list[LoopTrajectory] | list[PathFlight]:
    """One checked flight of ``spec`` per robot, deterministic in ``seed``; plain ``ring`` is
    :func:`~common.data.synth.trajectory.make_trajectories` (the default dataset's flights,
    with ``ring`` limits); ``cfg`` defaults to :class:`FlightConfig`."""
    if spec.is_default:
        return make_trajectories(scene, robots, seconds, seed, ring or TrajectoryConfig(), region)
    cfg = cfg or FlightConfig()
    limits = cfg.check_limits(spec)
    out: list[PathFlight] = []
    for k in range(robots):
        rng = np.random.default_rng([seed, 111, k, FAMILIES.index(spec.family)])
        reason = ""
        for _ in range(cfg.attempts):
            f = draw_flight(region, spec, k, robots, seconds, rng, cfg)
            why = check_trajectory(scene, f, seconds, limits)
            if why is None and spec.aggressive:
                why = _check_accel(f, seconds, cfg.aggressive_accel)
            if why is None:
                out.append(f)
                break
            reason = why
        else:
            raise TrajectoryError(
                f"robot {k}: no valid {spec.name} flight in {cfg.attempts} draws ({reason})"
            )
    return out
