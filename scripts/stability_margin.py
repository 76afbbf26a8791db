#!/usr/bin/env python
"""Measure where fixed-step runs of spring networks blow up, against the stability check.

    python scripts/stability_margin.py               # full run (docs/stability.md + plot)
    python scripts/stability_margin.py --quick       # smoke test: small batch, few steps
    python scripts/stability_margin.py --scenes rope_net --integrators semi_implicit_euler

For each scene and integrator the script computes

* ``bound``: the step the config check derives from the spring network
  (:func:`mysim_jax.dynamics.stability.scene_network_stable_step`: every spring counted in
  all directions, a bound over all configurations); the check accepts steps up to
  ``NETWORK_STEP_SAFETY x bound``;
* ``initial``: the same computation with each spring acting only along its direction in
  the initial configuration (what the check used before; for comparison);

then runs ``--envs`` vmapped copies of the scene (float32) for ``--t-end`` seconds at
steps ``h = f x bound`` for each fraction ``f`` of ``--fractions``, every point mass and
body starting with a random velocity (uniform direction, speed uniform in [0, ``--speed``]
m/s; bodies also a random angular velocity up to ``--speed`` / their largest marker
offset), and counts the envs that blow up (any state not finite, or a position beyond
``POSITION_LIMIT`` m, at the end of the run). Once every env of a scene blows up, the
larger fractions are not run (``-`` in the table). One jit per step size.

Scenes: ``rope_net`` (``configs/rope_net.yaml``) and ``random_<seed>`` scenes drawn from
the config schema by :func:`mysim_jax.bench.stability_margin.random_scene` (by ``seed % 3``: a tree of unlike ropes, knots,
free springs and a body; a star of identical ropes from one knot, maybe to a body's marker;
a net of identical ropes held at its corners by anchors or bodies), random n_masses, EA,
damping, masses, linear or tension_only, slack or stretched, their stiffness and damping
scaled so that the semi-implicit Euler bound is ``--target`` x 0.5-1.5. A ``:spherical``
suffix gives every body an isotropic inertia of the same trace (no gyroscopic term), to
tell blow-ups of the bodies' rotation from the network's.

Writes a markdown report (``--out``, default ``docs/stability.md``) with the tables and a
plot of the blown-up fraction against ``h / bound`` next to it. The scenes, batches and
counting live in :mod:`mysim_jax.bench.stability_margin` (the tests use them too).
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from mysim_jax.bench.stability_margin import DEFAULT_TARGET, INTEGRATORS, measure, write_report  # noqa: E402

DEFAULT_FRACTIONS = (0.8, 0.9, 1.0, 1.05, 1.1, 1.2, 1.3, 1.4, 1.5, 1.7, 2.0, 2.5)
# random_2 (a net carried by four bodies) also with spherical bodies (no gyroscopic term):
# the two rows tell the bodies' rotation from the spring network (docs/stability.md)
DEFAULT_SCENES = ("rope_net", "random_1", "random_2", "random_2:spherical", "random_3", "random_4",
                  "random_5", "random_6")


def build_parser() -> argparse.ArgumentParser:
    """The command line's parser (the documented-commands test parses with it)."""
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--envs", type=int, default=1024)
    parser.add_argument("--speed", type=float, default=10.0, help="largest initial speed [m/s]")
    parser.add_argument("--t-end", type=float, default=2.0)
    parser.add_argument("--fractions", default=",".join(f"{f:g}" for f in DEFAULT_FRACTIONS),
                        help="steps as fractions of the check's bound")
    parser.add_argument("--scenes", default=None,
                        help="rope_net, random_<seed>, optionally :spherical (bodies with equal moments)")
    parser.add_argument("--integrators", default=",".join(INTEGRATORS))
    parser.add_argument("--target", type=float, default=DEFAULT_TARGET,
                        help="random scenes: semi-implicit Euler bound to scale to [s] (x 0.5-1.5 per seed)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--quick", action="store_true", help="64 envs, 0.5 s, 3 fractions, 2 scenes")
    parser.add_argument("--out", type=Path, default=None,
                        help="markdown report (default docs/stability.md; --quick: docs/stability_quick.md)")
    return parser


def main(argv=None):
    args = build_parser().parse_args(argv)
    args.argv = list(sys.argv[1:] if argv is None else argv)
    if args.quick:
        args.envs, args.t_end = 64, 0.5
        args.fractions = "0.9,1.5,2.5"
        args.scenes = args.scenes or "rope_net,random_1"
    args.scenes = args.scenes or ",".join(DEFAULT_SCENES)
    out = args.out or ROOT / "docs" / ("stability_quick.md" if args.quick else "stability.md")
    fractions = [float(x) for x in args.fractions.split(",")]
    names = [x for x in args.scenes.split(",") if x]
    integrators = [x for x in args.integrators.split(",") if x]
    t0 = time.perf_counter()
    results, info = measure(names, integrators, fractions, args.envs, args.speed, args.t_end, args.target, args.seed)
    write_report(out, out.with_suffix(".png"), results, info, args, fractions, time.perf_counter() - t0)
    print(out.read_text())


if __name__ == "__main__":
    main()
