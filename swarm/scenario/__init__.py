"""The run's configuration and what a run is set up from: the TOML schema, its validation,
the command-line conventions, the seeded random streams and initial state, each drone's
core (``setup``) and the scene every step shows the drones (``scene``)."""
