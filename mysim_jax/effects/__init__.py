"""Optional physics a scene can have, each one registered effect (docs/effects.md): wind on
the quadrotors (``wind``), their body drag (``body_drag``), the gimbal cameras' servos
(``gimbal_servo``), the target's propulsion and behaviour (``target``) and its entanglement
in the net (``entanglement``); ``registry`` resolves the registry of effects at run time."""
