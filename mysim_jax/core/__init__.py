"""The bottom layer: vector maths (JAX and NumPy), random-number sites, the config base, the
Scene/Params/State containers and the batching and device-sharding primitives. Imports
nothing else from the package."""
