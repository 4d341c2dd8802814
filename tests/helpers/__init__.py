"""Helpers shared by the tests: processes, SITL boots, network namespaces, fuzzing, TLS."""
