"""Closed-loop tracking runs of the quadrotors' PID (``tracking``) and the gain tuning built
on them (``gains``): above the simulation loop, which they run."""
