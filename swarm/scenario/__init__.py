"""The run's configuration and what a run is set up from: the TOML schema, its validation,
the command-line conventions, the seeded random streams and initial state, each drone's
core (``setup``) and what the world shows the drones at every step (``world_step``)."""
