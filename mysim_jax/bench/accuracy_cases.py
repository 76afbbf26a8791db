"""The scenes and integrator settings of the accuracy-against-cost study (BENCHMARKS.md (d)).

An :class:`AccuracyCase` is one scene: its configuration, the quantity compared (e.g. the
payload's height, or the target's and the net knots' positions), the reference setting and
the :class:`Method` entries compared against it. :func:`accuracy_cases` lists them all (a
new scene is one more entry); ``quick`` keeps a few methods of each for a smoke test.
:mod:`mysim_jax.bench.accuracy` runs them; :class:`AccuracyRow` is one run's result.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np

from mysim_jax.bench.report import (
    CAPTURE_FALLING, COLLISION_HEAVY, COLLISION_LIGHT, ROPE_NET, ROPE_NET_SLACK,
)
from mysim_jax.tasks.scripted import team_policy


@dataclass(frozen=True)
class Method:
    """One integrator setting of the accuracy table."""

    integrator: str
    setting: str                       # "dt = 1e-4" / "rtol = 1e-8"
    overrides: tuple[str, ...]
    precision: str                     # float64 / float32
    max_steps: int | None = None       # cap for adaptive solvers (diffrax max_steps)
    note: str = ""
    step: float | None = None          # fixed-step integrators: the (sub-)step h [s]


def point_coordinate(point: str, axis: int) -> Callable:
    """Quantity: one coordinate of one point mass over time, ``(n_out,)``."""
    def quantity(scene, point_pos: np.ndarray, body_pos: np.ndarray) -> np.ndarray:
        return point_pos[:, scene.point_names.index(point), axis]
    return quantity


@dataclass(frozen=True)
class AccuracyCase:
    """One scene of the accuracy-vs-cost study.

    ``overrides`` apply to every run of the scene; ``reference`` is added on top for the
    reference solution; every entry of ``methods`` is added on top for the compared runs.
    ``quantity(scene, point_pos (n_out, n_points, 3), body_pos (n_out, n_bodies, 3))`` is
    what is compared: ``(n_out, ...)`` coordinates whose largest absolute difference is the
    error, or, with ``vector``, ``(n_out, k, 3)`` positions whose largest distance is.
    ``extra`` adds more such ``(label, quantity)`` errors as table columns.

    ``policy(config, scene)`` gives the control policy of every step (the same for every
    method; e.g. :func:`mysim_jax.tasks.scripted.team_policy`). ``reference_check`` is a
    second tight setting run like the reference; its distance to the reference is reported
    so that the reference's own error is known.
    """

    name: str
    config: Path
    quantity_label: str
    quantity: Callable
    t_end: float = 2.0
    reference_dt: float = 1e-3                     # output grid of the reference
    overrides: tuple[str, ...] = ()
    reference: tuple[str, ...] = ("sim.integrator=tsit5", "sim.rtol=1e-11", "sim.atol=1e-13",
                                  "sim.precision=float64")
    methods: tuple[Method, ...] = ()
    drift_tolerance: float | None = None           # report when the error first exceeds it
    tolerances: tuple[float, ...] = ()             # for tolerance_highlights
    policy: Callable | None = None                 # (config, scene) -> policy for rollout
    vector: bool = False
    extra: tuple[tuple[str, Callable], ...] = ()
    reference_check: tuple[str, ...] = ()
    notes: tuple[str, ...] = ()                    # paragraphs printed above the table
    order_note: bool = False                       # report the observed order of the fixed-step methods
    highlights: Callable | None = None             # (case, rows) -> markdown lines under the table


@dataclass
class AccuracyRow:
    """One method's row of an accuracy table: its status, error against the reference and cost."""

    case: str
    method: Method
    status: str                      # "ok" / "unstable (rejected)" / "diverged" / "failed: ..."
    error: float = float("nan")
    wall_per_sim_s: float = float("nan")
    compile_s: float = float("nan")
    n_repeats: int = 0
    drift_time: float | None = None  # first output time with error > case.drift_tolerance (None: never)
    extra_errors: tuple[float, ...] = ()   # errors of case.extra, in order


def fixed_step_methods(integrator: str, dts, precisions) -> list[Method]:
    """Fixed-step runs at each step ``dt`` (one sub-step per step) and precision."""
    out = []
    for dt in dts:
        for prec in precisions:
            out.append(Method(integrator, f"dt = {dt:.0e}", (f"sim.integrator={integrator}", f"sim.dt={dt:g}",
                                                           "sim.substeps=1"), prec, step=dt))
    return out


def substep_methods(integrator: str, env_dt: float, substeps, precisions) -> list[Method]:
    """Fixed-step runs that keep the env step ``sim.dt`` (the control period) and vary the
    physics sub-step ``h = env_dt / substeps``."""
    out = []
    for n in substeps:
        for prec in precisions:
            h = env_dt / n
            out.append(Method(integrator, f"h = {h:.2e} ({n} sub-steps)",
                              (f"sim.integrator={integrator}", f"sim.substeps={n}"), prec, step=h))
    return out


def adaptive_methods(integrator: str, rtols, precision: str, max_steps: int | None = None, note: str = "",
                     atol: float | None = None) -> list[Method]:
    """Adaptive runs at each rtol; atol = rtol / 100 unless given (then named in the setting)."""
    out = []
    for r in rtols:
        a = r * 1e-2 if atol is None else atol
        setting = f"rtol = {r:.0e}" + ("" if atol is None else f", atol = {a:.0e}")
        out.append(Method(integrator, setting, (f"sim.integrator={integrator}", f"sim.rtol={r:g}", f"sim.atol={a:g}"),
                          precision, max_steps, note))
    return out


def default_methods(quick: bool) -> tuple[Method, ...]:
    """The rope net: both explicit methods at five steps in both precisions, implicit_euler
    up to ten times the explicit limit, tsit5 at several tolerances and one capped kvaerno5."""
    if quick:
        return tuple(
            fixed_step_methods("semi_implicit_euler", (5e-5, 1e-4, 2e-4), ("float64",))
            + fixed_step_methods("semi_implicit_euler", (1e-4,), ("float32",))
            + fixed_step_methods("rk4", (1e-4, 3e-4), ("float64",))
            + fixed_step_methods("implicit_euler", (1e-3,), ("float64",))
            + adaptive_methods("tsit5", (1e-8,), "float64")
        )
    dts = (2e-5, 5e-5, 1e-4, 2e-4, 3e-4)
    return tuple(
        fixed_step_methods("semi_implicit_euler", dts, ("float64", "float32"))
        + fixed_step_methods("rk4", dts, ("float64", "float32"))
        # linearly implicit springs: from the explicit range up to ~10x the explicit limit
        + fixed_step_methods("implicit_euler", (2e-5, 1e-4, 3e-4, 1e-3), ("float64",))
        + fixed_step_methods("implicit_euler", (1e-4, 1e-3), ("float32",))
        + adaptive_methods("tsit5", (1e-6, 1e-8, 1e-10), "float64")
        # float32 resolves ~1e-7 relative: the config rejects tolerances below 1e-6 there
        # (config.FLOAT32_MIN_TOLERANCE); these are the tightest and a looser float32 setting
        + adaptive_methods("tsit5", (1e-6,), "float32", max_steps=200_000, atol=1e-6)
        + adaptive_methods("tsit5", (1e-5,), "float32", max_steps=200_000, atol=1e-5)
        # implicit solver, observed very slow on this scene: one loose tolerance, capped
        + adaptive_methods("kvaerno5", (1e-4,), "float64", max_steps=60_000,
                           note="max_steps capped at 60,000; not reached")
    )


def ball_and_payload_z(scene, point_pos: np.ndarray, body_pos: np.ndarray) -> np.ndarray:
    """Quantity of the contact scenes: z of the ball and of the payload, ``(n_out, 2)``."""
    return point_pos[:, [scene.point_names.index("ball"), scene.point_names.index("payload")], 2]


def target_position(scene, point_pos: np.ndarray, body_pos: np.ndarray) -> np.ndarray:
    """Quantity of the capture scene: the target's position, ``(n_out, 1, 3)``."""
    return body_pos[:, [scene.body_names.index("target")]]


def target_and_knots(scene, point_pos: np.ndarray, body_pos: np.ndarray) -> np.ndarray:
    """Quantity of the capture scene: the target's and every net knot's position,
    ``(n_out, 1 + n_knots, 3)`` (knots are the points named ``net_k*``; the lines' interior
    masses and the tethers' are left out)."""
    knots = [i for i, n in enumerate(scene.point_names) if n.startswith("net_k")]
    return np.concatenate([target_position(scene, point_pos, body_pos), point_pos[:, knots]], axis=1)


def contact_methods(quick: bool, light: bool) -> tuple[Method, ...]:
    """The contact scenes: the default (tsit5 rtol 1e-12, float64) against looser tolerances, the
    fixed-step paths (``substeps: auto`` = the stable step chosen from the contact
    stiffness, and finer steps), float32, and the implicit kvaerno5."""
    auto = [Method(i, "dt = 1e-3, substeps auto", (f"sim.integrator={i}", "sim.dt=0.001", "sim.substeps=auto"), p)
            for i, p in (("semi_implicit_euler", "float64"), ("semi_implicit_euler", "float32"),
                         ("rk4", "float64"), ("rk4", "float32"))]
    float32_tsit5 = adaptive_methods("tsit5", (1e-5,), "float32", max_steps=400_000, atol=1e-5)
    # the heavy scene's chattering contact makes loose tolerances hit-or-miss: the same
    # tolerance with another initial step (dt0 = sim.dt) shows how robust each one is
    dt0 = [Method("tsit5", f"rtol = {r:.0e}, dt0 = {h:.0e}", ("sim.integrator=tsit5", f"sim.rtol={r:g}",
                                                          f"sim.atol={r * 1e-2:g}", f"sim.dt={h:g}"), "float64")
           for r in (1e-11, 1e-12) for h in (5e-4, 2e-4)]
    if quick:
        return tuple(adaptive_methods("tsit5", (1e-12,), "float64") + auto[:1] + float32_tsit5)
    return tuple(
        adaptive_methods("tsit5", (1e-9, 1e-10, 1e-11, 1e-12), "float64")
        + ([] if light else dt0)
        + float32_tsit5
        + auto
        + fixed_step_methods("rk4", (2e-6,), ("float64",))
        + fixed_step_methods("semi_implicit_euler", (1e-6,), ("float64",))
        # implicit: measured >100x slower than tsit5 on the light scene; one tolerance, capped
        + (adaptive_methods("kvaerno5", (1e-6,), "float64", max_steps=60_000, note="max_steps capped at 60,000")
           if light else [])
    )


def slack_methods(quick: bool) -> tuple[Method, ...]:
    """The slack-rope net: fixed steps from the stability limit down (for the observed
    order across slack-taut switches), adaptive tsit5 and one capped kvaerno5."""
    if quick:
        return tuple(fixed_step_methods("semi_implicit_euler", (1e-4,), ("float64",))
                     + fixed_step_methods("rk4", (5e-5, 1e-4), ("float64",))
                     + adaptive_methods("tsit5", (1e-8,), "float64"))
    return tuple(
        fixed_step_methods("semi_implicit_euler", (5e-6, 2e-5, 5e-5, 1e-4, 2e-4), ("float64",))
        + fixed_step_methods("semi_implicit_euler", (2e-5, 1e-4), ("float32",))
        + fixed_step_methods("rk4", (5e-6, 2e-5, 5e-5, 1e-4, 2e-4), ("float64",))
        + fixed_step_methods("rk4", (2e-5, 1e-4), ("float32",))
        + adaptive_methods("tsit5", (1e-6, 1e-8, 1e-10), "float64")
        + adaptive_methods("tsit5", (1e-5,), "float32", max_steps=200_000, atol=1e-5)
        + adaptive_methods("kvaerno5", (1e-4,), "float64", max_steps=60_000, note="max_steps capped at 60,000")
    )


STIFF_EA = 1e9     # N: the stiff rope net's lines (10,000x the paper's EA)
STIFF_ROPES = tuple(f"ropes.{i}.EA={STIFF_EA:g}" for i in range(4))


def stiff_methods(quick: bool) -> tuple[Method, ...]:
    """The stiff rope net: explicit methods at steps near their stability limit (~4e-6 s
    for semi-implicit Euler) and implicit_euler from 25x to 500x that limit."""
    if quick:
        return tuple(fixed_step_methods("semi_implicit_euler", (3e-6,), ("float64",))
                     + fixed_step_methods("implicit_euler", (1e-3,), ("float64",)))
    return tuple(
        fixed_step_methods("semi_implicit_euler", (1e-6, 2e-6, 3e-6, 5e-6), ("float64",))
        + fixed_step_methods("semi_implicit_euler", (3e-6,), ("float32",))
        + fixed_step_methods("rk4", (2e-6, 4e-6), ("float64",))
        + fixed_step_methods("implicit_euler", (1e-4, 3e-4, 1e-3, 2e-3), ("float64",))
        + fixed_step_methods("implicit_euler", (1e-3, 2e-3), ("float32",))
        + adaptive_methods("tsit5", (1e-6,), "float64", max_steps=3_000_000)
        + adaptive_methods("kvaerno5", (1e-4,), "float64", max_steps=20_000,
                           note="max_steps capped at 20,000; not reached")
    )


# The capture scene's target spawn is drawn from a PRNG key, and the draw differs between
# float32 and float64: the accuracy runs fix it (to the float32 draw of the scene's seed,
# rounded) so that every method starts from the same state.
CAPTURE_SPAWN = ("target.spawn.position.low=[1.03,-0.95,6.23]", "target.spawn.position.high=[1.03,-0.95,6.23]",
                 "target.spawn.velocity.low=[-0.3,-0.29,0.29]", "target.spawn.velocity.high=[-0.3,-0.29,0.29]")
CAPTURE_DT = 2e-3        # the capture scene's env step (control period), kept for every method
TSIT5_CAPTURE: list[Method] = []   # tsit5 rtol 1e-6 per control period: > 5 min for 1.6 s, not run


def capture_methods(quick: bool) -> tuple[Method, ...]:
    """The capture scene: sub-steps of the fixed 2 ms control period from the stability
    limit (semi-implicit Euler 51, RK4 26; below that the builder rejects) down, and
    adaptive tsit5 on each control period."""
    if quick:
        return tuple(substep_methods("semi_implicit_euler", CAPTURE_DT, (51,), ("float32",)))
    return tuple(
        substep_methods("semi_implicit_euler", CAPTURE_DT, (40,), ("float64",))
        + substep_methods("semi_implicit_euler", CAPTURE_DT, (51,), ("float64", "float32"))
        + substep_methods("semi_implicit_euler", CAPTURE_DT, (102, 204), ("float64",))
        + substep_methods("rk4", CAPTURE_DT, (20,), ("float64",))
        + substep_methods("rk4", CAPTURE_DT, (26,), ("float64", "float32"))
        + substep_methods("rk4", CAPTURE_DT, (52, 104), ("float64",))
        # implicit net springs; contact and the tethers on the UAVs stay explicit (auto: 33)
        + substep_methods("implicit_euler", CAPTURE_DT, (33,), ("float64", "float32"))
        + substep_methods("implicit_euler", CAPTURE_DT, (66,), ("float64",))
        + TSIT5_CAPTURE
    )


def tolerance_highlights(case: AccuracyCase, rows: list[AccuracyRow]) -> list[str]:
    """The cheapest run within each of ``case.tolerances``, for the main error and each
    ``case.extra`` error."""
    ok = [r for r in rows if r.status == "ok"]
    out = []
    measures = [(case.quantity_label.split(" [")[0], lambda r: r.error)] + [
        (label, (lambda i: lambda r: r.extra_errors[i])(i)) for i, (label, _) in enumerate(case.extra)]
    for label, error in measures:
        for tol in case.tolerances:
            cands = sorted((r for r in ok if error(r) <= tol), key=lambda r: r.wall_per_sim_s)
            if cands:
                r = cands[0]
                out.append(f"- cheapest run with {label} within {tol:g} m: **{r.method.integrator} {r.method.setting} "
                           f"{r.method.precision}** ({error(r):.1e} m, {r.wall_per_sim_s:.3f} s per simulated s)")
            else:
                out.append(f"- no run has {label} within {tol:g} m")
    out += [f"- {r.method.integrator} {r.method.setting} {r.method.precision}: {r.status}" for r in rows
            if r.status != "ok"]
    return out + [""]


def accuracy_cases(quick: bool) -> list[AccuracyCase]:
    """The scenes of part (d): the rope net (as configured, with slack ropes, with stiff
    lines), the contact scenes and the closed-loop capture scene."""
    contact = (COLLISION_LIGHT,) if quick else (COLLISION_LIGHT, COLLISION_HEAVY)   # quick: a smoke test
    return _rope_net_cases(quick) + [_contact_case(config, quick) for config in contact] + [_capture_case(quick)]


def _rope_net_cases(quick: bool) -> list[AccuracyCase]:
    """The rope net as configured, with slack tension-only ropes, and with stiff lines."""
    rope_net = AccuracyCase(
        name="rope_net",
        config=ROPE_NET,
        quantity_label="payload z [m]",
        quantity=point_coordinate("payload", 2),
        t_end=2.0,
        methods=default_methods(quick),
        order_note=True,
    )
    return [
        rope_net,
        AccuracyCase(
            name="rope_net_slack",
            config=ROPE_NET_SLACK,
            quantity_label="payload position [m]",
            quantity=lambda scene, point_pos, body_pos: point_pos[:, [scene.point_names.index("payload")]],
            vector=True,
            t_end=2.0,
            reference_check=("sim.integrator=tsit5", "sim.rtol=1e-12", "sim.atol=1e-14", "sim.precision=float64"),
            methods=slack_methods(quick),
            order_note=True,
            tolerances=(1e-2, 1e-3, 1e-4, 1e-6),
            highlights=tolerance_highlights,
            notes=("`model: tension_only` ropes whose anchors are 0.71 m from the payload (rope length 1 m): "
                   "they start slack, the payload falls about 0.6 m, the ropes snap taut and it bounces; over 2 s "
                   "the 24 rope segments switch between slack and taut about 360 times (tsit5 reference). At "
                   "every switch the force has a kink (spring) and a jump (the damper, 50 N s/m, switches on "
                   "at once).",),
        ),
        dataclasses.replace(
            rope_net,
            name="rope_net_stiff",
            order_note=False,
            overrides=STIFF_ROPES,
            reference=("sim.integrator=tsit5", "sim.rtol=1e-10", "sim.atol=1e-12", "sim.precision=float64",
                       "sim.max_steps=3000000"),
            reference_check=("sim.integrator=rk4", "sim.dt=1e-6", "sim.substeps=1", "sim.precision=float64"),
            methods=stiff_methods(quick),
            tolerances=(1e-2, 5e-3, 1e-3, 1e-5),
            highlights=tolerance_highlights,
            notes=(f"The rope net with every line 10,000x stiffer (`ropes.*.EA={STIFF_EA:g}`; each of the 6 segments "
                   "of a line is a 6e9 N/m spring: a Dyneema line of EA 1e7 N lumped every 1.7 mm would be as stiff). "
                   "The payload's motion (its fall, the bounce, the net's transverse swing) stays slow, "
                   "but the axial modes of the lines are 100x faster than on the paper's net, so every explicit method is held "
                   "to steps of a few microseconds by stability, not accuracy. implicit_euler takes the lines "
                   "implicitly (the net has no contact and no body markers, so nothing explicit limits its step).",),
        ),
    ]


def _contact_case(config: Path, quick: bool) -> AccuracyCase:
    """A contact scene (``configs/collision_*.yaml``): ball and payload z, friction off."""
    return AccuracyCase(
        name=config.stem,
        config=config,
        quantity_label="ball and payload z [m]",
        quantity=ball_and_payload_z,
        t_end=1.5,
        overrides=("contact.friction=null",),      # friction off for the comparison
        reference=("sim.integrator=tsit5", "sim.rtol=1e-13", "sim.atol=1e-15", "sim.precision=float64",
                   "sim.max_steps=3000000"),
        methods=contact_methods(quick, light=config is COLLISION_LIGHT),
        drift_tolerance=2e-3,
        notes=("Friction is off in every run (`contact.friction=null`; on the scene's symmetry axis the slip is "
               "zero anyway).",),
    )


def _capture_case(quick: bool) -> AccuracyCase:
    """The closed-loop capture scene: the target's and the net knots' positions."""
    return AccuracyCase(
        name="capture_falling",
        config=CAPTURE_FALLING,
        quantity_label="target and net-knot positions [m]",
        quantity=target_and_knots,
        vector=True,
        extra=(("target", target_position),),
        t_end=1.6,
        reference_dt=1e-2,
        overrides=CAPTURE_SPAWN,
        reference=("sim.integrator=rk4", f"sim.substeps={52 if quick else 400}", "sim.precision=float64"),
        reference_check=() if quick else ("sim.integrator=rk4", "sim.substeps=200", "sim.precision=float64"),
        methods=capture_methods(quick),
        policy=team_policy,
        drift_tolerance=1e-2,
        order_note=True,
        tolerances=(1e-2, 1e-3),
        highlights=tolerance_highlights,
        notes=("Closed loop: every method runs the scene's scripted team policy "
               "(`mysim_jax.tasks.scripted.team_policy`) and cascaded PID once per 2 ms control period "
               "(`sim.dt` is kept; the methods differ in `sim.substeps` or, for tsit5, in one adaptive diffrax "
               "solve per control period). The target falls from 6.2 m, hits the net at about 1.2 s and "
               "sinks into it; tethers and net lines are tension-only, so they switch between slack and taut "
               "all along. The error is over the target and the 121 net knots (3-D distance); the target alone "
               "is the second error column. The target's spawn is fixed (`target.spawn` low = high) so that "
               "float32 and float64 runs start alike.",),
    )
