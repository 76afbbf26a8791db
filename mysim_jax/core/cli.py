"""Command-line pieces the scripts share (argparse only: no JAX, nothing heavy).

``--set`` takes one or more ``KEY=VALUE`` overrides after one flag, and the flag may be
repeated; both spellings give the same list, in the order typed::

    --set run.seed=1 run.eval_episodes=500
    --set run.seed=1 --set run.eval_episodes=500

Every word after ``--set`` up to the next flag is an override, so a positional argument
typed after the overrides (``--set a=1 CONFIG``) would be read as one: such a word (no
``=``) is an error that says to put it before ``--set`` or after ``--``.
"""

from __future__ import annotations

import argparse


def override(text: str) -> str:
    """argparse type of one ``--set`` value: ``KEY=VALUE`` with a non-empty key."""
    key, sep, _ = text.partition("=")
    if not sep or not key.strip():
        raise argparse.ArgumentTypeError(
            f"'{text}' is not KEY=VALUE (every word after --set up to the next flag is an override: put the "
            "file before --set, or end the overrides with --)")
    return text


def add_set_argument(parser: argparse.ArgumentParser, example: str = "sim.dt=5e-4",
                     what: str = "a config value") -> None:
    """Add ``--set KEY=VALUE [KEY=VALUE ...]`` (repeatable) to ``parser``; the overrides
    land in ``args.overrides`` (a list, empty by default)."""
    parser.add_argument("--set", dest="overrides", action="extend", nargs="+", type=override, default=[],
                        metavar="KEY=VALUE",
                        help=f"override {what}, e.g. --set {example}; several after one --set, or --set repeated")


def add_team_arguments(parser: argparse.ArgumentParser, episodes_help: str = "number of episodes (>= 1)") -> None:
    """The options of a script that flies capture teams on episodes (``evaluate.py``,
    ``sweep.py``): ``--policy`` (required), ``--compare``, ``--episodes`` (required),
    ``--out`` (required), ``--batch`` and ``--allow-mismatch``."""
    parser.add_argument("--policy", required=True, help="scripted, random, a trained policy folder (RUN/policy), "
                        "or a Python file defining make_policy")
    parser.add_argument("--compare", metavar="POLICY",
                        help="also run this team (as --policy) on the same episodes and compare (paired)")
    parser.add_argument("--episodes", type=int, required=True, help=episodes_help)
    parser.add_argument("--out", required=True, help="output directory (created if missing)")
    parser.add_argument("--batch", type=int, default=None, help="environments run side by side (default 64, "
                        "at most --episodes)")
    parser.add_argument("--allow-mismatch", action="store_true",
                        help="fly a trained policy on a scene whose setpoints, policy rate, action scale, observation "
                        "layout or target differ from those it was trained on (a deliberate test; refused otherwise)")
