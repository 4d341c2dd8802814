"""The run's configuration: the TOML schema, its validation and the command-line conventions."""
