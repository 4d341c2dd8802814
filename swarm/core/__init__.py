"""Pure numerical core: no I/O, no globals; numpy arrays in and out (SPEC §3-§10)."""
