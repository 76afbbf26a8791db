"""mysim_jax: a JAX-vectorised, differentiable multibody simulator of quadrotor teams
carrying a tethered net (docs/library.md is the map of the package)."""
