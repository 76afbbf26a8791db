"""Where the gradient map's windows start: the segments of a capture episode.

An episode is flown once by the scripted team (no gradients); from the states it passes
(``s_0`` the reset state, ``s_k`` after policy step ``k``) each segment picks the policy
step its windows start at, so that the window's first step holds the segment's event:

* ``free``: step 0, the target still far above the net (every episode spawns it there)
  and nothing touching;
* ``tether``: the first step in which a tether segment switches between slack and taut
  (its strain changes sign between ``s_k`` and ``s_{k+1}``); before the target first
  touches the net where an episode has such a switch, else the first one after it (the
  scripted team keeps its tethers taut in free flight, so the first switch often comes
  with the net's rebound after the contact);
* ``contact``: the step in which the target first touches a net line (``s_{k+1}`` the
  first state where the environment's ``touching`` flag is set).

An episode without the event (no switch, a target that never touches the net) has no
window in that segment. A window of ``h`` seconds covers the policy steps
from its start on; long windows from ``free`` run through the contact too: the segment
names where a window starts, and the short windows are the ones confined to it.
"""

from __future__ import annotations

import numpy as np

SEGMENTS = ("free", "tether", "contact")


def segment_starts(touching, taut) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """Per segment, ``(start, valid)`` ``(n_episodes,)``: the policy step each episode's
    window starts at and whether the episode has the segment (module docstring).
    ``touching`` ``(n_episodes, n_steps)`` and ``taut`` ``(n_episodes, n_steps,
    n_tether_segments)``: the flags of ``s_1 .. s_n``."""
    touching = np.asarray(touching, bool)
    taut = np.asarray(taut, bool)
    n_episodes, n_steps = touching.shape
    touched = touching.any(axis=1)
    first_touch = np.where(touched, touching.argmax(axis=1), n_steps)
    # switch between s_k and s_{k+1} for k >= 1 (flags of s_1 .. s_n: index k-1 and k)
    switch = np.zeros((n_episodes, n_steps), bool)
    switch[:, 1:] = (taut[:, 1:] != taut[:, :-1]).any(axis=-1)
    # switch[:, j]: between s_j and s_{j+1}, i.e. in policy step j
    before = switch & (np.arange(n_steps)[None, :] < first_touch[:, None])
    first = np.where(before.any(axis=1), before.argmax(axis=1), switch.argmax(axis=1))
    has_switch = switch.any(axis=1)
    return {"free": (np.zeros(n_episodes, int), ~touching[:, 0]),
            "tether": (np.where(has_switch, first, 0), has_switch),
            "contact": (np.where(touched, first_touch, 0), touched)}
