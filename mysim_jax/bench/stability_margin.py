"""The stability-margin measurement: random spring networks, randomised batches, blow-up counts.

``scripts/stability_margin.py`` writes ``docs/stability.md`` from :func:`measure`;
``tests/test_stability.py`` runs the same scenes and batches at the step the check
accepts. What is measured (the random scene families, the initial velocities, what
counts as a blow-up) is described in the script's docstring.
"""

from __future__ import annotations

import dataclasses
import datetime as _dt
import math
import shlex
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import yaml
from tqdm.auto import tqdm
import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

from mysim_jax.build import build
from mysim_jax.config.scene import ConfigError, config_from_dict
from mysim_jax.core.machine import machine
from mysim_jax.dynamics.stability import NETWORK_STEP_SAFETY, scene_network_stable_step
from mysim_jax.sim import rollout

ROPE_NET = Path(__file__).resolve().parents[2] / "configs" / "rope_net.yaml"
POSITION_LIMIT = 1e3        # m: no scene here gets near it in 2 s unless it blows up
INTEGRATORS = ("semi_implicit_euler", "rk4")
SHORT = {"semi_implicit_euler": "SIE", "rk4": "RK4"}
DEFAULT_TARGET = 2e-4       # s, semi-implicit Euler bound the random scenes are scaled to

# =========================================================================================
# scenes
# =========================================================================================


def rope_net_raw() -> dict:
    return yaml.safe_load(ROPE_NET.read_text())


def _log_uniform(rng, lo, hi):
    return float(np.exp(rng.uniform(np.log(lo), np.log(hi))))


def _vec(x):
    return [float(v) for v in x]


def _rope(rng, name, start, end, dist, ea, n_max=8, like=None):
    """A rope's config; ``like``: copy n_masses, mass, damping, model from that rope."""
    if like is not None:
        return {**like, "name": name, "start": start, "end": end,
                "length": max(dist, 0.05) * float(rng.uniform(0.9, 1.1)), "EA": ea}
    damping = 0.0 if rng.uniform() < 0.3 else ea * _log_uniform(rng, 1e-6, 1e-3)
    return {"name": name, "start": start, "end": end, "length": max(dist, 0.05) * float(rng.uniform(0.8, 1.2)),
            "n_masses": int(rng.integers(1, n_max + 1)), "mass": _log_uniform(rng, 0.01, 0.5), "EA": ea,
            "damping": damping, "model": str(rng.choice(["linear", "tension_only"]))}


def _body(rng, name, pos, n_markers):
    a = float(rng.uniform(0.005, 0.02))
    return {"name": name, "mass": float(rng.uniform(0.5, 2.0)),
            "inertia": [a, a * float(rng.uniform(1.0, 1.5)), a * float(rng.uniform(1.0, 1.5))], "pos": _vec(pos),
            "markers": [{"name": f"m{j}", "pos": _vec(rng.uniform(-0.3, 0.3, 3))} for j in range(n_markers)]}


class _SceneBuilder:
    """A raw scene dict being drawn, with the initial position of everything a rope can end on."""

    def __init__(self, rng, raw: dict):
        self.rng, self.raw, self.positions = rng, raw, {}

    def add_point(self, name, pos):
        self.raw["points"].append({"name": name, "mass": _log_uniform(self.rng, 0.05, 1.0), "pos": _vec(pos)})
        self.positions[name] = np.asarray(pos, float)

    def add_anchor(self, name, pos):
        self.raw["anchors"].append({"name": name, "pos": _vec(pos)})
        self.positions[name] = np.asarray(pos, float)

    def add_body(self, name, pos, n_markers):
        body = _body(self.rng, name, pos, n_markers)
        self.raw["bodies"].append(body)
        for m in body["markers"]:
            self.positions[f"{name}.{m['name']}"] = np.asarray(pos) + np.asarray(m["pos"])
        return [f"{name}.{m['name']}" for m in body["markers"]]

    def add_rope(self, start, end, ea, n_max=8, like=None):
        pos = self.positions
        r = _rope(self.rng, f"r{len(self.raw['ropes'])}", start, end, float(np.linalg.norm(pos[start] - pos[end])),
                  ea, n_max, like)
        self.raw["ropes"].append(r)
        n = r["n_masses"]
        for j in range(n):
            pos[f"{r['name']}_{j}"] = pos[start] + (j + 0.5) / n * (pos[end] - pos[start])
        return [f"{r['name']}_{j}" for j in range(n)]


def random_scene(seed: int) -> dict:
    """A random spring network built from the config schema (raw dict, before scaling).

    ``seed % 3`` picks the family: 0 a *tree* (anchors, knots and an optional body joined
    by ropes with their own n_masses, mass, EA, damping and law, ropes starting on earlier
    ropes' masses, free springs); 1 a *star* (a knot with three to six identical ropes to
    anchors in random directions, one maybe to a body's marker: the rope net, randomised);
    2 a *net* (a grid of knots joined by identical ropes, its corners tethered to anchors
    or to markers on bodies, one body possibly holding two corners).
    """
    rng = np.random.default_rng(seed)
    raw = {"name": f"random_{seed}", "sim": {"t_end": 1.0, "dt": 1e-3, "output_dt": 1e-3},
           "anchors": [], "points": [], "bodies": [], "ropes": [], "springs": []}
    (_tree, _star, _net)[seed % 3](_SceneBuilder(rng, raw))
    return raw


def _tree(b: _SceneBuilder) -> None:
    rng, raw = b.rng, b.raw
    ends, free = [], []
    for i in range(int(rng.integers(1, 4))):
        b.add_anchor(f"a{i}", rng.uniform(-1, 1, 3))
        ends.append(f"a{i}")
    for i in range(int(rng.integers(1, 4))):
        b.add_point(f"k{i}", rng.uniform(-1, 1, 3))
        ends.append(f"k{i}")
        free.append(f"k{i}")
    if rng.uniform() < 0.6:
        markers = b.add_body("body", rng.uniform(-1, 1, 3), int(rng.integers(1, 3)))
        ends += markers
        free += markers
    for _ in range(int(rng.integers(2, 6))):
        start = str(rng.choice(free))
        masses = b.add_rope(start, str(rng.choice([e for e in ends if e != start])), _log_uniform(rng, 1e3, 1e6))
        ends += masses
        free += masses
    for i in range(int(rng.integers(0, 3))):
        start = str(rng.choice(free))
        raw["springs"].append({"name": f"s{i}", "start": start, "end": str(rng.choice([e for e in ends if e != start])),
                               "stiffness": _log_uniform(rng, 1e3, 1e5), "damping": float(rng.uniform(0, 20)),
                               "model": str(rng.choice(["linear", "tension_only"]))})


def _star(b: _SceneBuilder) -> None:
    rng, raw = b.rng, b.raw
    ea = _log_uniform(rng, 1e3, 1e6)
    module = _rope(rng, "", "", "", 1.0, ea, n_max=6)         # every rope alike, like a net's
    raw["points"].append({"name": "hub", "mass": module["mass"] * float(rng.uniform(0.5, 2.0)), "pos": [0.0] * 3})
    b.positions["hub"] = np.zeros(3)
    n_ropes = int(rng.integers(3, 7))
    body_rope = int(rng.integers(0, n_ropes)) if rng.uniform() < 0.4 else -1
    for i in range(n_ropes):
        d = rng.standard_normal(3)
        pos = d / np.linalg.norm(d) * rng.uniform(0.5, 1.5)
        if i == body_rope:
            end = b.add_body("body", pos, 1)[0]
        else:
            b.add_anchor(f"a{i}", pos)
            end = f"a{i}"
        b.add_rope("hub", end, ea, like=module)


def _net(b: _SceneBuilder) -> None:
    rng, raw = b.rng, b.raw
    nx, ny = int(rng.integers(2, 5)), int(rng.integers(2, 5))
    spacing = float(rng.uniform(0.3, 0.6))
    ea = _log_uniform(rng, 1e3, 1e6)
    module = _rope(rng, "", "", "", 1.0, ea, n_max=3)
    knot = module["mass"] * float(rng.uniform(0.5, 2.0))
    for i in range(nx):
        for j in range(ny):
            raw["points"].append({"name": f"k{i}_{j}", "mass": knot, "pos": [i * spacing, j * spacing, 0.0]})
            b.positions[f"k{i}_{j}"] = np.array([i * spacing, j * spacing, 0.0])
    for i in range(nx):
        for j in range(ny):
            if i + 1 < nx:
                b.add_rope(f"k{i}_{j}", f"k{i + 1}_{j}", ea, like=module)
            if j + 1 < ny:
                b.add_rope(f"k{i}_{j}", f"k{i}_{j + 1}", ea, like=module)
    corners = ["k0_0", f"k{nx - 1}_0", f"k0_{ny - 1}", f"k{nx - 1}_{ny - 1}"]
    kind = int(rng.integers(0, 3))      # 0 anchors, 1 a body (UAV) per corner, 2 one body holds two
    shared = b.add_body("carrier", [0.5 * (nx - 1) * spacing, -0.5, 1.0], 2) if kind == 2 else []
    for c, corner in enumerate(corners):
        above = b.positions[corner] + np.array([0.0, 0.0, 1.0]) + rng.uniform(-0.3, 0.3, 3)
        if kind == 1:
            end = b.add_body(f"uav{c}", above, 1)[0]
        elif kind == 2 and c < 2:
            end = shared[c]
        else:
            b.add_anchor(f"a{c}", above)
            end = f"a{c}"
        b.add_rope(corner, end, ea, like=module)


def scale_network(raw: dict, factor: float) -> dict:
    """Stiffness x factor², damping x factor: every explicit limit scales by 1 / factor."""
    raw = yaml.safe_load(yaml.safe_dump(raw))
    for r in raw.get("ropes", []):
        r["EA"] *= factor ** 2
        r["damping"] = r.get("damping", 0.0) * factor
    for s in raw.get("springs", []):
        s["stiffness"] *= factor ** 2
        s["damping"] = s.get("damping", 0.0) * factor
    return raw


def built(raw: dict, integrator: str):
    """``(scene, params, state)`` in float32 at a step far below any limit."""
    cfg = config_from_dict(raw, raw["name"], [f"sim.integrator={integrator}", "sim.precision=float32",
                                              "sim.dt=1e-7", "sim.output_dt=1e-7", "sim.t_end=1e-7",
                                              "sim.substeps=1"])
    return build(cfg)


def _rotate(q, v):
    w, u = q[..., :1], q[..., 1:]
    t = 2.0 * np.cross(u, v)
    return v + w * t + np.cross(u, t)


def limits(scene, params, state, integrator):
    """``(bound, initial)``: the check's network bound, and the initial-direction estimate."""
    p = jax.tree.map(lambda x: np.asarray(x, dtype=float), params)
    s = jax.tree.map(lambda x: np.asarray(x, dtype=float), state.phys)
    mb = np.asarray(scene.marker_body, dtype=np.int64)
    markers = (s.body_pos[mb] + _rotate(s.body_quat[mb], p.marker_pos)).reshape(-1, 3)
    node_pos = np.concatenate([s.point_pos.reshape(-1, 3), markers, p.anchor_pos.reshape(-1, 3)])
    args = (integrator, scene, p.point_mass, p.body_mass, p.body_inertia, p.marker_pos,
            p.spring_stiffness, p.spring_damping)
    return scene_network_stable_step(*args)[0], scene_network_stable_step(*args, node_pos=node_pos)[0]


def scene_for(name: str, target: float):
    """Raw config of scene ``name``; random scenes scaled to a semi-implicit Euler bound of
    ``target`` s (times a per-seed factor in [0.5, 1.5]). ``<name>:spherical`` replaces
    every body's inertia by the isotropic one with the same trace."""
    base, _, variant = name.partition(":")
    if base == "rope_net":
        raw = rope_net_raw()
    else:
        seed = int(base.split("_")[1])
        attempt = 0
        while True:
            raw = random_scene(seed + 1000 * attempt)
            raw["name"] = base
            try:
                scene, params, state = built(raw, "semi_implicit_euler")
                break
            except ConfigError:
                attempt += 1
        bound, _ = limits(scene, params, state, "semi_implicit_euler")
        raw = scale_network(raw, bound / (target * np.random.default_rng(seed).uniform(0.5, 1.5)))
    if variant == "spherical":
        for body in raw.get("bodies", []):
            body["inertia"] = [float(np.trace(np.asarray(_inertia(body["inertia"])))) / 3.0] * 3
    elif variant:
        raise ValueError(f"unknown scene variant {variant!r} in {name!r}")
    return raw


def _inertia(value):
    return np.diag(value) if np.ndim(value) == 1 else np.asarray(value, float)


def describe(raw: dict, scene) -> str:
    ropes = raw.get("ropes", [])
    models = sorted({r.get("model", "tension_only") for r in ropes} | {s.get("model", "linear") for s in raw.get("springs", [])})
    bodies = raw.get("bodies", [])
    text = (f"{scene.n_points} point masses, {len(ropes)} ropes, {len(raw.get('springs', []))} free springs "
            f"({scene.n_springs} springs), {', '.join(models)}")
    if bodies:
        masses = ", ".join(f"{b['mass']:.2g} kg" for b in bodies)
        text += (f", {len(bodies)} bodies ({masses}) with "
                 f"{sum(len(b.get('markers', [])) for b in bodies)} markers")
    return text


# =========================================================================================
# runs
# =========================================================================================


def random_states(scene, params, state, n_envs: int, speed: float, key):
    """``n_envs`` copies of ``state`` with random velocities (see the module docstring)."""
    def ball(key, shape, radius):
        k1, k2 = jax.random.split(key)
        d = jax.random.normal(k1, shape + (3,))
        d = d / jnp.linalg.norm(d, axis=-1, keepdims=True)
        return d * (radius * jax.random.uniform(k2, shape + (1,)))

    kp, kb, kw = jax.random.split(key, 3)
    states = jax.tree.map(lambda x: jnp.broadcast_to(x, (n_envs,) + x.shape), state)
    phys = states.phys
    dtype = phys.point_pos.dtype
    phys = phys.replace(point_vel=ball(kp, (n_envs, scene.n_points), speed).astype(dtype))
    if scene.n_bodies:
        reach = np.full(scene.n_bodies, 0.1)       # largest marker offset (at least 0.1 m)
        offsets = np.linalg.norm(np.asarray(params.marker_pos, float).reshape(-1, 3), axis=1)
        for m, b in enumerate(scene.marker_body):
            reach[b] = max(reach[b], offsets[m])
        phys = phys.replace(body_vel=ball(kb, (n_envs, scene.n_bodies), speed).astype(dtype),
                            body_angvel=(ball(kw, (n_envs, scene.n_bodies), 1.0)
                                         * jnp.asarray(speed / reach)[None, :, None]).astype(dtype))
    return states.replace(phys=phys)


def blown_up(final) -> np.ndarray:
    """``(n_envs,)`` bool: any state not finite, or a position beyond POSITION_LIMIT."""
    bad = None
    for leaf in jax.tree.leaves(final.phys):
        x = np.asarray(leaf).reshape(leaf.shape[0], -1)
        b = ~np.isfinite(x).all(axis=1)
        bad = b if bad is None else bad | b
    for pos in (final.phys.point_pos, final.phys.body_pos):
        x = np.nan_to_num(np.asarray(pos).reshape(pos.shape[0], -1), nan=0.0, posinf=np.inf, neginf=-np.inf)
        bad |= (np.abs(x) > POSITION_LIMIT).any(axis=1)
    return bad


def count_blow_ups(scene, params, states, h: float, t_end: float) -> int:
    n_steps = int(math.ceil(t_end / h - 1e-9))
    sc = dataclasses.replace(scene, dt=h, substeps=1)
    run = jax.jit(jax.vmap(lambda s: rollout(sc, params, s, n_steps, n_steps)[0]))
    return int(blown_up(run(states)).sum())


def measure(names, integrators, fractions, n_envs, speed, t_end, target, seed):
    """Blow-up counts ``{(scene, integrator): {fraction: count or None}}`` and scene info."""
    raws = {name: scene_for(name, target) for name in names}
    results, info = {}, {}
    total = len(names) * len(integrators) * len(fractions)
    bar = tqdm(total=total, desc="runs", unit="run")
    for name in names:
        for integrator in integrators:
            scene, params, state = built(raws[name], integrator)
            bound, initial = limits(scene, params, state, integrator)
            info[(name, integrator)] = {"bound": bound, "initial": initial, "describe": describe(raws[name], scene)}
            states = random_states(scene, params, state, n_envs, speed, jax.random.PRNGKey(seed))
            row, all_blown = {}, False
            for f in fractions:
                bar.set_postfix_str(f"{name} {SHORT[integrator]} h = {f:g} x bound")
                row[f] = None if all_blown else count_blow_ups(scene, params, states, f * bound, t_end)
                all_blown = all_blown or row[f] == n_envs
                bar.update(1)
            results[(name, integrator)] = row
    bar.close()
    return results, info


def onset(row):
    """``(largest fraction with no blow-up below the first one, first fraction with any)``."""
    first = next((f for f in sorted(row) if row[f]), None)
    safe = max((f for f in sorted(row) if (first is None or f < first)), default=None)
    return safe, first


def write_report(path: Path, plot: Path, results, info, args, fractions, elapsed) -> None:
    """The markdown report (tables of bounds, blow-ups per step, their onset) at ``path``
    and its plot at ``plot``. ``args``: the run's settings (``argv``, ``envs``, ``t_end``,
    ``speed``, ``seed``), as ``scripts/stability_margin.py`` parses them."""
    lines = _table_lines(results, info, args, fractions, elapsed) + _onset_lines(results, info, fractions)
    lines += ["", f"![blown-up fraction against h / bound]({plot.name})", ""]
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text("\n".join(lines))

    plot_margins(plot, results, args, fractions)


def _table_lines(results, info, args, fractions, elapsed) -> list[str]:
    names = list(dict.fromkeys(n for n, _ in results))
    integrators = list(dict.fromkeys(i for _, i in results))
    lines = [
        "# Stability margin of the spring-network check",
        "",
        f"Generated by `{' '.join(['python scripts/stability_margin.py'] + [shlex.quote(a) for a in args.argv])}`"
        f" on {_dt.date.today().isoformat()} (jax {jax.__version__}, {jax.devices()[0].platform}, "
        f"{elapsed / 60:.0f} min on {machine()}). Do not edit by hand: rerun the script.",
        "",
        f"Each run: {args.envs} envs (vmap), float32, {args.t_end:g} s, every point mass and body starting "
        f"with a random velocity (uniform direction, speed uniform in [0, {args.speed:g}] m/s; bodies also an "
        f"angular velocity up to {args.speed:g} m/s over their largest marker offset), PRNG seed {args.seed}. "
        f"An env *blows up* if any state is not finite or a position exceeds {POSITION_LIMIT:g} m at the end. "
        "Steps are given as fractions of `bound`, the step the check computes from the spring network "
        "with every spring counted in all directions (a bound over all configurations, "
        "`mysim_jax/dynamics/stability.py`); the check accepts steps up to "
        f"**{NETWORK_STEP_SAFETY:g} x bound**. `initial` is the same computation with each spring acting "
        "only along its initial direction (what the check used before). `-`: not run, every env had "
        "already blown up at a smaller step.",
        "",
        "## Scenes",
        "",
        "| scene | what | " + " | ".join(f"{SHORT[i]} bound [s] | {SHORT[i]} initial [s]" for i in integrators) + " |",
        "|---|---|" + "---:|---:|" * len(integrators),
    ]
    for n in names:
        cells = []
        for i in integrators:
            x = info[(n, i)]
            cells += [f"{x['bound']:.3g}", f"{x['initial']:.3g} ({x['initial'] / x['bound']:.2f}x)"]
        lines.append(f"| {n} | {info[(n, integrators[0])]['describe']} | " + " | ".join(cells) + " |")
    for i in integrators:
        lines += ["", f"## {SHORT[i]}: envs blown up (of {args.envs}) at h / bound", "",
                  "| scene | " + " | ".join(f"{f:g}" + (" (accepted)" if f <= NETWORK_STEP_SAFETY + 1e-12 else "")
                                          for f in fractions) + " |",
                  "|---|" + "---:|" * len(fractions)]
        for n in names:
            row = results[(n, i)]
            lines.append(f"| {n} | " + " | ".join("-" if row[f] is None else str(row[f]) for f in fractions) + " |")
    return lines


def _onset_lines(results, info, fractions) -> list[str]:
    lines = []
    lines += ["", "## Onset of blow-ups", "",
              "First step with any blow-up, as a fraction of `bound`, of the accepted step and of `initial`, "
              "and the largest step below it with none.", "",
              "| scene | integrator | accepted step [s] | none up to (x bound) | first blow-ups at (x bound) | "
              "same, x accepted | same, x initial |",
              "|---|---|---:|---:|---:|---:|---:|"]
    for (n, i), row in results.items():
        safe, first = onset(row)
        x = info[(n, i)]
        lines.append(f"| {n} | {SHORT[i]} | {NETWORK_STEP_SAFETY * x['bound']:.3g} | "
                     f"{safe if safe is not None else '-'} | {first if first is not None else f'> {max(fractions):g}'} | "
                     + (f"{first / NETWORK_STEP_SAFETY:.2f} | {first * x['bound'] / x['initial']:.2f}"
                        if first is not None else "- | -") + " |")
    accepted = [(n, i, f, v) for (n, i), row in results.items() for f, v in row.items()
                if v and f <= NETWORK_STEP_SAFETY + 1e-12]
    at_bound = [(n, i, f, v) for (n, i), row in results.items() for f, v in row.items()
                if v and f <= 1.0 + 1e-12]
    lines += ["", f"Blow-ups at steps the check accepts (h <= {NETWORK_STEP_SAFETY:g} x bound): "
              + ("**none**" if not accepted else ", ".join(f"{n} {SHORT[i]} {v} at {f:g} x bound"
                                                          for n, i, f, v in accepted)) + "; "
              + "at steps up to the bound itself: "
              + ("none" if not at_bound else ", ".join(f"{n} {SHORT[i]} {v} at {f:g} x bound"
                                                      for n, i, f, v in at_bound)) + ".",
              "",
              "A `:spherical` scene is the same scene with every body's inertia made isotropic (same trace), "
              "which removes the gyroscopic term ω × Iω: comparing the two rows tells blow-ups of the bodies' "
              "rotation from blow-ups of the spring network. (Semi-implicit Euler takes that term implicitly; "
              "taken explicitly, a fast-spinning body with unequal moments gains energy every step, and "
              "random_2 blew up at 0.9 x bound.)"]
    return lines


def plot_margins(plot: Path, results, args, fractions) -> None:
    """The fraction of environments blown up against the step, per integrator."""
    names = list(dict.fromkeys(n for n, _ in results))
    integrators = list(dict.fromkeys(i for _, i in results))
    fig, axes = plt.subplots(1, len(integrators), figsize=(5.5 * len(integrators), 4), squeeze=False)
    for ax, i in zip(axes[0], integrators):
        for n in names:
            row = results[(n, i)]
            fs = [f for f in fractions if row[f] is not None]
            ax.plot(fs, [row[f] / args.envs for f in fs], "o-", ms=3, label=n)
        ax.axvline(NETWORK_STEP_SAFETY, color="k", ls="--", lw=1, label="accepted up to")
        ax.set_xlabel("h / bound")
        ax.set_ylabel("fraction of envs blown up")
        ax.set_title(f"{SHORT[i]}, {args.envs} envs, v <= {args.speed:g} m/s, {args.t_end:g} s")
        ax.grid(alpha=0.3)
    axes[0][0].legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(plot, dpi=120)
    plt.close(fig)


