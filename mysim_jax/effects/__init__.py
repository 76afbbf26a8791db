"""Optional physics a scene can have, each one registered object (``registry``): the
contact broad phase, line drag, the target's propulsion and behaviour (``target``) and
its entanglement in the net (``entanglement``)."""
