"""Penalty contact between spheres, with the ground plane (paper Sec. 2.1), and between
spheres and capsules on rope and spring segments.

* :mod:`~mysim_jax.contact.config` — the ``contact:`` block of a scene file;
* :mod:`~mysim_jax.contact.law` — normal force (IMPACT-style, Hermite damping ramp),
  C¹ friction law, and their smooth variants;
* :mod:`~mysim_jax.core.contact_types` — static :class:`ContactScene`, traced :class:`ContactParams`;
* :mod:`~mysim_jax.contact.build` — host-side assembly and explicit stability limit;
* :mod:`~mysim_jax.contact.forces` — the ``contact_forces`` stage of the force pipeline;
* :mod:`~mysim_jax.contact.energy` — mechanical energy of a state (for checks).

This package's ``__init__`` imports nothing: :mod:`mysim_jax.config.scene` imports
``mysim_jax.contact.config`` while it is itself being imported.
"""
