"""Scene files as typed, validated models: the scene (``scene``), its quadrotors
(``quadrotor``), the capture task's target and team (``capture``) and its environment
(``env``). Pydantic, PyYAML and NumPy only: validating a file never imports JAX."""
