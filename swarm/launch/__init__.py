"""Launch: the launch-swarm command and the supervisor that starts, watches and stops a swarm."""
