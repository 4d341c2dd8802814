"""Recordings: one run as ``DIR/run.mcap`` (MCAP), what it holds (``schema``), written as the run
goes (``writer``) and read back (``reader``)."""
